"""The Schmidt-Kalman (consider) update of the localizer against a fixed map."""

from dataclasses import replace
import math

from landmark_ros.core import sensors
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.localizer import motion
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.consider import (ConsiderRows, ConsiderSlots, select,
                                             update_consider, widen)
from landmark_ros.localizer.localizer import Localizer
from landmark_ros.localizer.mixture import update_mixture
from landmark_ros.localizer.steps import Batch
from landmark_ros.localizer.update import observe, RANGE, RANGE_BEARING, update, UpdateSettings
import numpy as np
import pytest

MS = 1_000_000
ONE_STEP = UpdateSettings(chi2_threshold(1, 0.999999), chi2_threshold(2, 0.999999),
                          'consider', iterate_threshold=1e9, max_iterations=1)


def _spd(rng, n, scale):
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + np.eye(n) * scale ** 2 * 0.1


def _joint(rng, n=3, landmarks=2):
    """Return a state, a map and a joint covariance whose cross block is not zero."""
    x = np.array([0.3, -0.2, 0.4] + [0.01] * (n - 3))
    m = rng.uniform(2.0, 5.0, size=(landmarks, 2)) * rng.choice([-1, 1], size=(landmarks, 2))
    J = _spd(rng, n + 2 * landmarks, 0.1)
    for k in range(landmarks):  # the map's covariance is block diagonal
        for j in range(landmarks):
            if j != k:
                J[n + 2 * k:n + 2 * k + 2, n + 2 * j:n + 2 * j + 2] = 0.0
    J = J + np.eye(len(J)) * 0.05  # still positive definite
    return x, m, J


@pytest.mark.parametrize('n', [3, 5])
def test_the_update_is_the_schmidt_update_of_the_joint_state(n):
    """Landmark 0 seen twice and landmark 1 once, one partial row; against the joint EKF."""
    rng = np.random.default_rng(n)
    x, m, J = _joint(rng, n)
    P, C = J[:n, :n], J[:n, n:]
    P_m = np.array([J[n:n + 2, n:n + 2], J[n + 2:, n + 2:]])
    rows = np.array([0, 1, 0])
    kind = np.array([RANGE_BEARING, RANGE_BEARING, RANGE])
    R = np.array([_spd(rng, 2, 0.05) for _ in rows])
    h, _, _ = observe(x, m[rows])
    z = h + rng.normal(0.0, 0.05, h.shape)
    result = update_consider(x, P, C, ConsiderRows(rows, m[rows], P_m[rows]), z, R, kind,
                             ONE_STEP)
    # the joint model: y = (x, m0, m1); the stacked components and their Jacobian
    comps = [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0)]
    _, J_z_x, J_z_m = observe(x, m[rows])
    Hj = np.zeros((len(comps), n + 4))
    Rs = np.zeros((len(comps), len(comps)))
    nu = np.zeros(len(comps))
    for a, (i, c) in enumerate(comps):
        Hj[a, :n] = J_z_x[i, c]
        Hj[a, n + 2 * rows[i]:n + 2 * rows[i] + 2] = J_z_m[i, c]
        nu[a] = motion.wrap(z[i, c] - h[i, c])
        for b, (k, d) in enumerate(comps):
            Rs[a, b] = R[i, c, d] if i == k else 0.0
    S = Hj @ J @ Hj.T + Rs
    K = np.zeros((n + 4, len(comps)))
    K[:n] = (J @ Hj.T @ np.linalg.inv(S))[:n]  # Schmidt: the landmarks are not updated
    A = np.eye(n + 4) - K @ Hj
    J_new = A @ J @ A.T + K @ Rs @ K.T
    x_new = x + K[:n] @ nu
    np.testing.assert_allclose(result.x, x_new, atol=1e-10)
    np.testing.assert_allclose(result.P, J_new[:n, :n], atol=1e-10)
    np.testing.assert_allclose(result.C, J_new[:n, n:], atol=1e-10)
    np.testing.assert_allclose(J_new[n:, n:], J[n:, n:], atol=1e-10)  # the map stays
    assert result.nis == pytest.approx(nu @ np.linalg.solve(S, nu), rel=1e-10)
    assert result.dof == 5 and result.used.all()


@pytest.mark.parametrize('near', [False, True])
def test_without_cross_covariance_the_first_update_is_the_plain_ekf(near):
    """Also iterated: landmarks 1 m away, a precise sensor and a loose heading."""
    rng = np.random.default_rng(2)
    x, m, J = _joint(rng)
    P_m = np.array([J[3:5, 3:5], J[5:, 5:]])
    R = np.array([_spd(rng, 2, 0.05)] * 2)
    if near:
        m = x[:2] + (m - x[:2]) / np.linalg.norm(m - x[:2], axis=1)[:, None]
        R = np.array([np.diag([1e-4, 1e-4])] * 2)
        P_m = np.zeros((2, 2, 2))  # ``update`` keeps the map term of the first step
        J[2, 2] += 0.25
    z = observe(x + np.array([0.2, -0.2, 0.5]) * near, m)[0] + rng.normal(0.0, 0.01, (2, 2))
    kind = np.array([RANGE_BEARING, RANGE_BEARING])
    settings = replace(ONE_STEP, iterate_threshold=0.1, max_iterations=5)
    a = update_consider(x, J[:3, :3], None, ConsiderRows(np.array([0, 1]), m, P_m), z, R, kind,
                        settings)
    b = update(x, J[:3, :3], m, P_m, z, R, kind, replace(settings, correlation='independent'))
    np.testing.assert_allclose(a.x, b.x, atol=1e-12)
    np.testing.assert_allclose(a.P, b.P, atol=1e-12)
    assert a.iterations == b.iterations and a.nis == pytest.approx(b.nis, rel=1e-12)
    assert (a.iterations > 1) == near
    assert a.C.shape == (3, 4) and np.any(a.C) != near  # C - K G P_m: zero without P_m


def test_the_gate_counts_the_cross_terms():
    """A pose known to move with the landmark leaves a small innovation covariance."""
    x = np.zeros(3)
    m = np.array([[3.0, 0.0]])
    P_m = np.eye(2)[None] * 0.04
    P = np.diag([0.04, 0.04, 1e-6])
    C = np.eye(3)[:, :2] * 0.039  # correlation 0.975 between pose and landmark
    R = np.eye(2)[None] * 1e-4
    kind = np.array([RANGE_BEARING])
    settings = replace(ONE_STEP, gate_2=chi2_threshold(2, 0.99))
    far = observe(x, m + [0.5, 0.0])[0]  # S_rr 0.0801 alone, 0.0021 with the cross terms
    plain = update_consider(x, P, None, ConsiderRows(np.array([0]), m, P_m), far, R, kind,
                            settings)
    joint = update_consider(x, P, C, ConsiderRows(np.array([0]), m, P_m), far, R, kind,
                            settings)
    assert plain.used[0] and not plain.gated[0]
    assert joint.gated[0] and not joint.used[0]
    near = observe(x, m + [0.02, 0.0])[0]
    assert update_consider(x, P, C, ConsiderRows(np.array([0]), m, P_m), near, R, kind,
                           settings).used[0]


def test_predict_cross_is_the_cross_block_of_the_augmented_prediction():
    rng = np.random.default_rng(5)
    for _ in range(10):
        x, _, J = _joint(rng, 4)
        delta, Q = rng.normal(size=3) * 0.3, _spd(rng, 3, 0.05)
        x_aug = np.concatenate([x, np.zeros(4)])
        _, J_next = motion.predict_with(x_aug, J, delta, Q)
        np.testing.assert_allclose(motion.predict_cross(x, J[:4, 4:], delta), J_next[:4, 4:],
                                   atol=1e-14)
    assert motion.predict_cross(x, None, delta) is None


def test_slots_and_widen():
    slots = ConsiderSlots()
    np.testing.assert_array_equal(slots.slots(np.array([7, 3, 7])), [0, 1, 0])
    np.testing.assert_array_equal(slots.slots(np.array([9, 3])), [2, 1])
    assert slots.width == 6
    C = widen(np.ones((3, 2)), 3, 6)
    assert C.shape == (3, 6) and C[:, 2:].sum() == 0.0
    assert widen(None, 4, 2).shape == (4, 2)
    C = np.arange(18.0).reshape(3, 6)
    columns = slots.retain([9, 7, 8])              # 3 (slot 1) leaves
    np.testing.assert_array_equal(columns, [0, 1, 4, 5])
    np.testing.assert_array_equal(select(C, columns), C[:, [0, 1, 4, 5]])
    np.testing.assert_array_equal(slots.slots(np.array([7, 9, 3])), [0, 1, 2])
    assert select(C[:, :2], columns)[:, 2:].sum() == 0.0   # narrower: zero columns
    assert select(C, slots.retain([])).shape == (3, 0) and slots.width == 0
    assert select(None, columns) is None


def test_the_mixture_collapses_the_cross_covariance_with_the_weights():
    rng = np.random.default_rng(8)
    x, m, J = _joint(rng)
    m[1] = m[0] + [0.05, -0.03]  # two candidates the row fits
    P_m = np.array([J[3:5, 3:5], J[5:, 5:]])
    z = observe(x, m[:1])[0] + 0.01
    beta = np.array([0.7, 0.3])
    batch = Batch(0, m[:1], P_m[:1], z, np.eye(2)[None] * 0.01, np.array([RANGE_BEARING]),
                  alternatives={0: (m, P_m, beta, np.array([10, 11]))},
                  landmarks=np.array([10]))
    slots = ConsiderSlots()

    def rows(x_, P_, C_, b):
        return update_consider(x_, P_, C_, ConsiderRows(slots.slots(b.landmarks), b.m, b.P_m),
                               b.z, b.R, b.kind, ONE_STEP)
    out = update_mixture(x, J[:3, :3], J[:3, 3:], batch, rows)
    parts = [update_consider(x, J[:3, :3], J[:3, 3:], ConsiderRows(np.array([j]), m[j:j + 1],
                                                                   P_m[j:j + 1]),
                             z, batch.R, batch.kind, ONE_STEP) for j in (0, 1)]
    assert parts[0].used[0] and parts[1].used[0]
    np.testing.assert_allclose(out.C, 0.7 * parts[0].C + 0.3 * parts[1].C, atol=1e-14)
    np.testing.assert_allclose(out.x, 0.7 * parts[0].x + 0.3 * parts[1].x, atol=1e-14)


def _drive(seed, correlation, steps=900, map_stddev=0.08):
    """
    Drive a robot on a circle among 6 landmarks whose map is off by N(0, map_stddev).

    The sensor is precise (1 cm, 5 mrad) against the map: the map's error dominates and
    is the same at every sighting. Returns the pose NEES every 5 steps after 100.
    """
    rng = np.random.default_rng(seed)
    truth = np.array([[4.0, 0.0], [0.0, 4.0], [-4.0, 0.0], [0.0, -4.0], [3.0, 3.0],
                      [-3.0, -3.0]])
    cfg = LocalizerConfig(odometry_alphas=(0.2, 1.0, 0.2, 0.05), range_stddev=0.01,
                          range_stddev_per_m=0.0, bearing_stddev=0.005,
                          initial_stddev=(0.05, 0.05, 0.02), correlation=correlation)
    loc = Localizer(cfg)
    P_m = np.tile(np.eye(2) * map_stddev ** 2, (len(truth), 1, 1))
    loc.set_map(np.arange(len(truth)), truth + rng.normal(0.0, map_stddev, truth.shape), P_m)
    x = np.array([2.0, 0.0, math.pi / 2])
    loc.initialize(0, x + rng.normal(0, cfg.initial_stddev),
                   np.diag(np.square(cfg.initial_stddev)))
    loc.add_odometry(0, twist=np.array([0.4, 0.2]))
    nees, t = [], 0
    for k in range(steps):
        d = motion.delta_from_twist(0.4, 0.2, 0.02)
        Q = motion.odometry_noise(d, cfg.odometry_alphas) + np.eye(3) * 1e-14
        x = motion.compose(x, d + rng.multivariate_normal(np.zeros(3), Q))
        t += 20 * MS
        loc.add_odometry(t, twist=np.array([0.4, 0.2]))
        if k % 3 == 0:
            ids = rng.permutation(len(truth))[:2]
            z = sensors.observe(np.tile(x, (2, 1)), truth[ids])
            z += rng.normal(0, [0.01, 0.005], z.shape)
            loc.add_observations(t, ids, z, np.array([RANGE_BEARING, RANGE]))
        if k > 100 and k % 5 == 0:
            est = loc.estimate()
            e = est.x - x
            e[2] = motion.wrap(e[2])
            nees.append(e @ np.linalg.solve(est.P, e))
    return float(np.mean(nees))


def test_against_a_map_off_by_its_covariance_only_consider_is_consistent():
    """Independent counts the map's error again at every sighting, split CI pays too much."""
    seeds = range(16)
    anees = {c: np.mean([_drive(s, c) for s in seeds])
             for c in ('consider', 'independent', 'split_ci')}
    assert 2.2 < anees['consider'] < 3.9, anees
    assert anees['independent'] > 8.0, anees
    assert anees['split_ci'] < 0.7 * anees['consider'], anees


def test_the_localizer_keeps_the_cross_covariance_through_refiltering():
    """Sightings applied late give what they give in order, cross-covariance included."""
    cfg = LocalizerConfig(correlation='consider', initial_stddev=(0.05, 0.05, 0.02))
    lm = np.array([[3.0, 1.0], [-2.0, 4.0]])
    out, locs = [], []
    for late in (False, True):
        loc = Localizer(cfg)
        locs.append(loc)
        loc.set_map(np.array([4, 9]), lm, np.tile(np.eye(2) * 0.01, (2, 1, 1)))
        loc.initialize(0, np.zeros(3), np.diag([0.0025, 0.0025, 0.0004]))
        sightings = [(100 * MS, np.array([4]), observe(np.zeros(3), lm[:1])[0] + 0.01),
                     (140 * MS, np.array([9]), observe(np.zeros(3), lm[1:])[0] - 0.01)]
        for k in range(1, 11):
            loc.add_odometry(k * 20 * MS, twist=np.array([0.0, 0.0]))
            if not late:
                for stamp, ids, z in sightings:
                    if stamp == k * 20 * MS:
                        loc.add_observations(stamp, ids, z)
        if late:
            for stamp, ids, z in reversed(sightings):
                loc.add_observations(stamp, ids, z)
        out.append(loc._steps[-1])
    assert out[0].C is not None and out[0].C.shape == (3, 4) and np.any(out[0].C)
    np.testing.assert_allclose(out[1].x, out[0].x, atol=1e-12)
    np.testing.assert_allclose(out[1].P, out[0].P, atol=1e-12)
    for i in (4, 9):  # the slots follow the order of first use: compare by ID
        a, b = (loc_._consider.slots(np.array([i]))[0] for loc_ in locs)
        np.testing.assert_allclose(out[1].C[:, 2 * b:2 * b + 2], out[0].C[:, 2 * a:2 * a + 2],
                                   atol=1e-12)


def test_the_monte_carlo_tool_draws_the_map_off_by_its_covariance():
    """``--map-stddev``: the same seeds, independent far above consider; 0 keeps the map."""
    from landmark_ros.eval.localization_montecarlo import run_seed
    seeds = range(6)
    consider = np.mean([run_seed(s, 20.0, map_stddev=0.1, correlation='consider')[0]
                        for s in seeds])
    independent = np.mean([run_seed(s, 20.0, map_stddev=0.1)[0] for s in seeds])
    assert 1.5 < consider < 4.5 and independent > 3.0 * consider, (consider, independent)
    assert run_seed(0, 5.0)[0] == run_seed(0, 5.0, map_stddev=0.0, correlation='independent')[0]


def test_a_new_map_keeps_the_cross_covariance_of_the_landmarks_that_stay():
    cfg = LocalizerConfig(correlation='consider', initial_stddev=(0.05, 0.05, 0.02))
    lm = np.array([[3.0, 1.0], [-2.0, 4.0], [1.0, -3.0]])
    loc = Localizer(cfg)
    loc.set_map(np.array([4, 9, 2]), lm, np.tile(np.eye(2) * 0.01, (3, 1, 1)))
    loc.initialize(0, np.zeros(3), np.diag([0.0025, 0.0025, 0.0004]))
    for k in range(1, 6):
        loc.add_odometry(k * 20 * MS, twist=np.array([0.1, 0.0]))
        loc.add_observations(k * 20 * MS, np.array([4, 9, 2]),
                             observe(np.array([0.002 * k, 0.0, 0.0]), lm)[0])
    before = loc._steps[-1].C.copy()
    slot = {i: int(loc._consider.slots(np.array([i]))[0]) for i in (4, 9, 2)}
    loc.set_map(np.array([2, 4, 7]), np.vstack([lm[[2, 0]], [[5.0, 5.0]]]),
                np.tile(np.eye(2) * 0.01, (3, 1, 1)))   # 9 left, 7 came
    after = loc._steps[-1].C
    assert after.shape == (3, 4) and loc._consider.width == 4
    for i in (4, 2):
        new = int(loc._consider.slots(np.array([i]))[0])
        np.testing.assert_array_equal(after[:, 2 * new:2 * new + 2],
                                      before[:, 2 * slot[i]:2 * slot[i] + 2])
    assert all(s.C is None or s.C.shape[1] == 4 for s in loc._steps)
    loc.add_odometry(6 * 20 * MS, twist=np.array([0.1, 0.0]))
    loc.add_observations(6 * 20 * MS, np.array([7]),
                         observe(np.zeros(3), np.array([[5.0, 5.0]]))[0])
    assert loc._steps[-1].C.shape == (3, 6)
