"""Tests of fuser.partial: partial rows in the Observer, views in the Fuser (no ROS)."""

import json
import math

from landmark_ros.core.gating import chi2_threshold
from landmark_ros.core.landmarks import sensor_in_world
from landmark_ros.core.partial import BEARING, RANGE, Views
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.observer.partial import CorrelatedNoise
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.pipeline.partial_rows import (PARTIAL_COLUMNS, PartialObservations,
                                                RANGE_SCALE_COLUMNS)
import numpy as np
import pytest
from scipy.stats import chi2

S = 1_000_000_000
P_POSE = np.diag([1e-4, 1e-4, 1e-5])
LANDMARKS = ['/r1/landmarks', '/r2/landmarks']
VIEWS = ['/r1/partial_observations', '/r2/partial_observations']


def columns(ids, kind, y, s, P_s=np.zeros((3, 3)), R=1e-6, R_bias=0.0, group=0):
    """Return partial observation columns of views (as the observer publishes them)."""
    views = Views(kind, s, P_s, y, R, R_bias)
    ids = np.broadcast_to(np.asarray(ids, np.int64), (len(views),)).copy()
    return PartialObservations(ids, views, np.full(len(views), group, np.int64)).columns()


def bearing_to(s, m):
    """Return the exact bearing of ``m`` from sensor pose ``s``."""
    return math.atan2(m[1] - s[1], m[0] - s[0]) - s[2]


def fuser(fusion='split_covariance_intersection', **values):
    """Return a fuser with two landmark and two partial sources."""
    return Fuser(FuserConfig(fusion=fusion, **values), LANDMARKS, partial_sources=VIEWS)


# --- Observer ----------------------------------------------------------------------------------

def test_bearing_only_cloud_gives_partial_observations_with_the_mounting_composed():
    mount = (0.2, -0.1, 0.3)
    observer = Observer(ObserverConfig(sensor_pose=mount, bearing_stddev=0.01,
                                       bearing_bias_stddev=0.005))
    pose = np.array([1.0, 2.0, 0.5])
    observer.add_pose(S, pose, P_POSE)
    batch, = observer.add_observations([ObservationMessage(
        S, {'id': np.array([4, 5]), 'bearing': np.array([0.1, -0.2])})])
    assert len(batch.ids) == 0
    c = batch.partial_observations
    np.testing.assert_array_equal(c.ids, [4, 5])
    np.testing.assert_array_equal(c.views.kind, [BEARING, BEARING])
    s, P_s = sensor_in_world(pose, P_POSE, np.array(mount))
    np.testing.assert_allclose(c.views.s, np.broadcast_to(s, (2, 3)), atol=1e-12)
    np.testing.assert_allclose(c.views.P_s, np.broadcast_to(P_s, (2, 3, 3)), atol=1e-15)
    np.testing.assert_allclose(c.views.R, 1e-4)
    np.testing.assert_allclose(c.views.R_bias, 0.005 ** 2)
    out = c.columns()
    assert tuple(out) == PARTIAL_COLUMNS + RANGE_SCALE_COLUMNS
    assert all(np.isfinite(np.asarray(v, dtype=float)).all() for v in out.values())
    assert observer.counters['partial_rows'] == 2
    assert observer.status().level == 'ok'


def test_range_only_cloud_with_per_row_variance():
    observer = Observer(ObserverConfig())
    observer.add_pose(S, np.zeros(3), P_POSE)
    batch, = observer.add_observations([ObservationMessage(
        S, {'id': np.array([1, 2, 3]), 'range': np.array([2.0, 0.0, 3.0]),
            'range_variance': np.array([0.04, 0.04, np.nan])})])
    c = batch.partial_observations
    np.testing.assert_array_equal(c.ids, [1, 3])
    np.testing.assert_array_equal(c.views.kind, [RANGE, RANGE])
    np.testing.assert_allclose(c.views.R, [0.04, 0.1 ** 2])
    assert observer.counters['range_not_positive'] == 1


def test_nan_in_a_range_bearing_row_makes_it_partial_not_rejected():
    observer = Observer(ObserverConfig())
    observer.add_pose(S, np.zeros(3), P_POSE)
    batch, = observer.add_observations([ObservationMessage(
        S, {'id': np.array([1, 2, 3, 4]), 'range': np.array([2.0, np.nan, 3.0, np.nan]),
            'bearing': np.array([0.1, 0.2, np.nan, np.nan])})])
    np.testing.assert_array_equal(batch.ids, [1])
    np.testing.assert_array_equal(batch.partial_observations.ids, [2, 3])
    np.testing.assert_array_equal(batch.partial_observations.views.kind, [BEARING, RANGE])
    assert observer.counters['partial_rows'] == 2
    assert observer.counters['observation_nonfinite'] == 1   # both NaN


def test_view_groups_differ_between_poses():
    observer = Observer(ObserverConfig())
    observer.add_pose(S, np.zeros(3), P_POSE)
    observer.add_pose(2 * S, np.ones(3), P_POSE)
    first, second = observer.add_observations([
        ObservationMessage(S, {'id': np.array([1, 2]), 'bearing': np.array([0.1, 0.2])}),
        ObservationMessage(2 * S, {'id': np.array([1]), 'bearing': np.array([0.3])})])
    assert len(set(first.partial_observations.view_group.tolist())) == 1
    assert first.partial_observations.view_group[0] != second.partial_observations.view_group[0]


# --- Fuser: initialisation ---------------------------------------------------------------------

@pytest.mark.parametrize('fusion', ['independent', 'covariance_intersection',
                                    'split_covariance_intersection'])
def test_two_exact_bearings_give_the_intersection(fusion):
    m = np.array([3.0, 4.0])
    f = fuser(fusion)
    for k, s in enumerate(([0.0, 0.0, 0.3], [6.0, 0.0, -0.2])):
        f.add_partial_observations(VIEWS[k], (k + 1) * S, columns(7, BEARING, bearing_to(s, m), s,
                                                                  P_s=P_POSE))
    f.fuse_queued()
    ids, mean, P, P_dep, _ = f.snapshot()
    np.testing.assert_array_equal(ids, [7])
    np.testing.assert_allclose(mean[0], m, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(P[0]) > 0)
    assert f.counters['landmarks_initialised'] == 1
    assert f.sources[VIEWS[0]].counts['partial_fused'] == 1


def test_statuses_count_the_views_waiting_per_source():
    m = np.array([3.0, 4.0])
    f = fuser()
    for k, s in enumerate(([0.0, 0.0, 0.3], [6.0, 0.0, -0.2], [1.0, 1.0, 0.0])):
        f.add_partial_observations(VIEWS[k % 2], (k + 1) * S,
                                   columns(7, BEARING, bearing_to(s, m), s, P_s=P_POSE))

    def waiting():
        return {status.name: status.extra['queued_partial'] for status in f.statuses(4 * S)
                if status.name}

    assert {name: waiting()[name] for name in VIEWS[:2]} == {VIEWS[0]: 2, VIEWS[1]: 1}
    f.fuse_queued()
    assert set(waiting().values()) == {0}


def test_three_exact_ranges_give_the_point():
    m = np.array([-1.0, 2.5])
    f = fuser()
    for k, s in enumerate(([0.0, 0.0, 0.0], [4.0, 0.0, 1.0], [0.0, 5.0, 2.0])):
        f.add_partial_observations(VIEWS[k % 2], (k + 1) * S,
                                   columns(3, RANGE, np.hypot(*(m - s[:2])), s, P_s=P_POSE,
                                           R=1e-4))
        f.fuse_queued()
    ids, mean, _, _, _ = f.snapshot()
    np.testing.assert_array_equal(ids, [3])
    np.testing.assert_allclose(mean[0], m, atol=1e-9)


def test_a_near_parallel_pair_waits():
    m = np.array([50.0, 0.0])
    f = fuser(min_triangulation_angle_deg=5.0)
    for k, s in enumerate(([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])):   # ~1.1 degrees apart
        f.add_partial_observations(VIEWS[k], (k + 1) * S, columns(1, BEARING, bearing_to(s, m), s))
    f.fuse_queued()
    assert len(f.map) == 0
    assert f.partial.wait_reasons['small_crossing_angle'] == 1
    s = [25.0, 40.0, 0.0]                                        # a wide third view
    f.add_partial_observations(VIEWS[0], 3 * S, columns(1, BEARING, bearing_to(s, m), s))
    f.fuse_queued()
    np.testing.assert_allclose(f.snapshot().m[0], m, atol=1e-6)


@pytest.mark.parametrize('fusion', ['independent', 'covariance_intersection',
                                    'split_covariance_intersection'])
def test_a_mixed_landmark(fusion, rng):
    m = np.array([2.0, 1.0])
    f = fuser(fusion, min_observations=1)
    for k, s in enumerate(([0.0, 0.0, 0.0], [4.0, 0.0, 0.0])):
        f.add_partial_observations(VIEWS[k], (k + 1) * S, columns(9, BEARING, bearing_to(s, m), s,
                                                                  P_s=P_POSE, R=1e-4))
    f.fuse_queued()
    before = f.snapshot()
    # A range-bearing landmark row of another robot fuses through the map.
    R = np.diag([1e-4, 1e-4])
    f.add_landmarks(LANDMARKS[1], LandmarkMessage(3 * S, [9], (m + [0.005, -0.005])[None], R[None],
                    0.5 * R[None]))
    f.fuse_queued()
    after = f.snapshot()
    assert after.observations[0] == before.observations[0] + 1
    assert np.linalg.det(after.P[0]) < np.linalg.det(before.P[0])
    # A range view updates it by the partial EKF.
    s = np.array([2.0, -3.0, 0.0])
    f.add_partial_observations(VIEWS[0], 4 * S, columns(9, RANGE, 4.0, s, P_s=P_POSE, R=1e-3))
    f.fuse_queued()
    last = f.snapshot()
    assert last.observations[0] == after.observations[0] + 1
    assert last.P[0][1, 1] <= after.P[0][1, 1] * (1 + 1e-9)   # CI may ignore a view
    assert f.sources[VIEWS[0]].counts['partial_fused'] == 2
    assert f.map.sources_of(9)


def test_views_update_a_landmark_range_bearing_rows_confirmed():
    f = fuser(min_observations=1)
    R = np.diag([0.04, 0.04])
    f.add_landmarks(LANDMARKS[0], LandmarkMessage(
        S, [5], np.array([[1.0, 1.0]]), R[None], 0.0 * R[None]))
    s = np.array([1.0, -2.0, 0.0])
    f.add_partial_observations(VIEWS[1], 2 * S, columns(5, BEARING, bearing_to(s, [1.0, 1.0]), s))
    f.fuse_queued()     # the views go first: the landmark is not yet there, the view waits
    f.add_partial_observations(VIEWS[1], 3 * S, columns(5, BEARING, bearing_to(s, [1.0, 1.0]), s))
    f.fuse_queued()
    assert f.sources[VIEWS[1]].counts['partial_superseded'] == 1
    assert f.sources[VIEWS[1]].counts['partial_fused'] == 1
    assert f.snapshot().P[0][0, 0] < 0.01


def test_an_outlier_view_is_gated_and_counted():
    m = np.array([3.0, 4.0])
    f = fuser()
    for k, s in enumerate(([0.0, 0.0, 0.0], [6.0, 0.0, 0.0])):
        f.add_partial_observations(VIEWS[k], (k + 1) * S, columns(7, BEARING, bearing_to(s, m), s,
                                                                  R=1e-4))
    f.add_partial_observations(VIEWS[0], 3 * S, columns(7, BEARING, bearing_to([0, 0, 0], m) + 0.5,
                                                        [0.0, 0.0, 0.0], R=1e-4))
    f.fuse_queued()
    assert f.sources[VIEWS[0]].counts['partial_gated'] == 1
    assert f.statuses(0)[0].level == 'warn'
    np.testing.assert_allclose(f.snapshot().m[0], m, atol=1e-9)


def test_waiting_views_are_bounded():
    f = fuser(max_views_per_landmark=3)
    for k in range(5):    # all from one place: never placed
        f.add_partial_observations(VIEWS[0], (k + 1) * S,
                                   columns(2, BEARING, 0.1, [0.0, 0.0, 0.0]))
    f.fuse_queued()
    assert len(f.partial.waiting[2]) == 3
    assert f.sources[VIEWS[0]].counts['partial_dropped'] == 2
    f.reset()
    assert not f.partial.waiting


def test_malformed_partial_observation_rows_are_rejected_with_counters():
    good = columns(np.arange(8), BEARING, 0.1, np.zeros((8, 3)), P_s=P_POSE)
    bad = {name: np.array(values, dtype=float if name not in ('id', 'kind', 'view_group')
                          else np.int64) for name, values in good.items()}
    bad['value'][0] = np.nan
    bad['id'][1] = -1
    bad['kind'][2] = 2
    bad['kind'][3], bad['value'][3] = RANGE, 0.0
    bad['variance'][4] = 0.0
    bad['variance_dep'][5] = -1.0
    bad['sensor_cov_xx'][6] = -1.0
    f = fuser()
    assert f.add_partial_observations(VIEWS[0], S, bad) == 1
    assert dict(f.sources[VIEWS[0]].counts) == {
        'messages_in': 1, 'partial_in': 8, 'partial_nonfinite': 1, 'invalid_id': 1,
        'invalid_kind': 1, 'range_not_positive': 1, 'variance_not_positive': 1,
        'variance_dep_negative': 1, 'sensor_covariance_not_psd': 1}
    assert f.add_partial_observations(VIEWS[0], S, good, frame_id='odom') == 0
    assert f.sources[VIEWS[0]].counts['wrong_frame'] == 1


def test_set_estimate_holds_the_estimate_for_every_method():
    for fusion in ('independent', 'covariance_intersection', 'split_covariance_intersection'):
        landmark_map = LandmarkMap(fusion, min_observations=1)
        P, P_dep = np.array([[0.04, 0.01], [0.01, 0.09]]), np.diag([0.01, 0.02])
        landmark_map.set_estimate(3, [1.0, 2.0], P, P_dep, 'views', 5, 2)
        ids, m, P_out, _, observations = landmark_map.snapshot()
        np.testing.assert_allclose(m[0], [1.0, 2.0], atol=1e-12)
        np.testing.assert_allclose(P_out[0], P, atol=1e-12)
        assert observations[0] == 2
        landmark_map.update([3], [[1.1, 2.0]], [np.diag([0.04, 0.04])], source='r1')
        assert landmark_map.snapshot().observations[0] == 3
        assert landmark_map.sources_of(3) == ['r1', 'views']


# --- Consistency -------------------------------------------------------------------------------

@pytest.mark.parametrize('kind', [BEARING, RANGE])
def test_nees_of_views_through_the_fuser(kind):
    """Monte Carlo: noisy poses and views; the ANEES lies in its 99.9 % interval."""
    rng = np.random.default_rng(11)
    runs, m_true = 200, np.array([2.0, 3.0])
    R = 0.02 ** 2 if kind == BEARING else 0.05 ** 2
    P_pose = np.diag([0.03 ** 2, 0.03 ** 2, 0.01 ** 2])
    nees = []
    for _ in range(runs):
        f = fuser('independent')
        for k in range(6):
            angle = rng.uniform(0, 2 * np.pi)
            true = np.array([*(m_true + rng.uniform(3, 6) * np.array(
                [np.cos(angle), np.sin(angle)])), rng.uniform(-np.pi, np.pi)])
            believed = true + rng.multivariate_normal(np.zeros(3), P_pose)
            y = (bearing_to(true, m_true) if kind == BEARING
                 else np.hypot(*(m_true - true[:2]))) + rng.normal(0, np.sqrt(R))
            f.add_partial_observations(VIEWS[k % 2], (k + 1) * S,
                                       columns(1, kind, y, believed, P_s=P_pose, R=R, group=k))
            f.fuse_queued()
        ids, m, P, _, _ = f.snapshot()
        if not len(ids):      # e.g. ranges whose circles still meet twice: waits
            continue
        d = m[0] - m_true
        nees.append(d @ np.linalg.solve(P[0], d))
    assert len(nees) >= 0.95 * runs
    anees, count = np.mean(nees), len(nees)
    low, high = chi2.ppf([0.0005, 0.9995], 2 * count) / count
    assert low <= anees <= high, anees
    assert chi2_threshold(2, 0.999) > np.median(nees)


def test_a_landmark_gated_again_and_again_is_placed_again_from_its_recent_views():
    old, new = np.array([3.0, 4.0]), np.array([5.0, 1.0])
    f = fuser(max_views_per_landmark=5, max_consecutive_rejections=5)
    for k, s in enumerate(([0.0, 0.0, 0.0], [6.0, 0.0, 0.0])):
        f.add_partial_observations(VIEWS[k], (k + 1) * S,
                                   columns(7, BEARING, bearing_to(s, old), s))
    f.fuse_queued()
    np.testing.assert_allclose(f.snapshot().m[0], old, atol=1e-9)
    for k, s in enumerate(([0.0, 0.0, 0.0], [9.0, 0.0, 0.0], [0.0, 6.0, 0.0],
                           [9.0, 6.0, 1.0], [2.0, -3.0, 0.0])):
        f.add_partial_observations(VIEWS[0], (k + 3) * S,
                                   columns(7, BEARING, bearing_to(s, new), s))
    f.fuse_queued()
    assert f.sources[VIEWS[0]].counts['partial_gated'] == 5
    assert f.counters['landmarks_reinitialised'] == 1
    np.testing.assert_allclose(f.snapshot().m[0], new, atol=1e-9)


# --- Time-correlated noise -------------------------------------------------------------------

def test_correlated_noise_factors():
    tau, f = 4.0, 0.75
    c = CorrelatedNoise(0.5, f, tau)
    first = c.factors(10 * S, np.array([3, 3, 4]), np.array([BEARING, RANGE, BEARING]))
    np.testing.assert_allclose(first, 1.0)          # first views of (id, kind)
    again = c.factors(12 * S, np.array([3, 4, 3]), np.array([BEARING, BEARING, RANGE]))
    coth = 1.0 / np.tanh(2.0 / (2.0 * tau))
    np.testing.assert_allclose(again, [(1 - f) + f * coth, (1 - f) + f * coth,
                                       0.5 + 0.5 * coth])
    late = c.factors(1000 * S, np.array([3]), np.array([BEARING]))
    np.testing.assert_allclose(late, 1.0, atol=1e-12)  # long after: independent again
    white = CorrelatedNoise(0.5, f, 0.0)
    assert not white.enabled
    np.testing.assert_array_equal(white.factors(S, np.array([3, 3]), np.array([1, 1])), 1.0)
    small = CorrelatedNoise(0.0, f, tau, max_landmarks=2)
    for k in range(5):
        small.factors(S, np.array([k]), np.array([BEARING]))
    assert len(small.last_ns) == 2 and (4, BEARING) in small.last_ns


@pytest.mark.parametrize('f', [0.3, 0.64, 0.94])
@pytest.mark.parametrize('dt', [0.05, 0.2, 1.0, 5.0])
def test_correlated_noise_weights_give_the_variance_of_the_mean(f, dt):
    """The weighted mean of AR(1) + white views: variance 1/sum(w) against the exact one."""
    tau, n = 8.0, 200
    c = CorrelatedNoise(f, f, tau)
    factor = np.concatenate([c.factors(int(k * dt * S), np.array([1]), np.array([BEARING]))
                             for k in range(n)])
    i = np.arange(n)
    C = f * np.exp(-np.abs(i[:, None] - i[None]) * dt / tau) + (1 - f) * np.eye(n)

    def ratio(w):          # claimed variance over true variance of the weighted mean
        return (1.0 / w.sum()) / (w @ C @ w / w.sum() ** 2)

    assert 0.8 <= ratio(1.0 / factor) <= 1.25
    if dt <= 1.0:          # the white model claims far less than the truth
        assert ratio(np.ones(n)) < 0.3


def ar1_errors(rng, times, tau, sigma, fraction):
    """Return white plus first-order Gauss-Markov errors at ``times`` [s]."""
    x, last, out = rng.standard_normal(), times[0], []
    for t in times:
        rho = math.exp(-(t - last) / tau)
        x = rho * x + math.sqrt(1.0 - rho * rho) * rng.standard_normal()
        last = t
        out.append(sigma * (math.sqrt(fraction) * x
                            + math.sqrt(1.0 - fraction) * rng.standard_normal()))
    return np.array(out)


@pytest.mark.parametrize('modelled, consistent', [(False, False), (True, True)])
def test_nees_with_time_correlated_bearing_noise(modelled, consistent):
    """Monte Carlo: a robot circling a landmark at 2 Hz with correlated bearing errors."""
    rng = np.random.default_rng(5)
    runs, m_true, sigma, tau, fraction = 40, np.array([1.0, 2.0]), 0.02, 5.0, 0.8
    times = np.arange(0.0, 20.0, 0.5)
    nees = []
    for _ in range(runs):
        observer = Observer(ObserverConfig(
            bearing_stddev=sigma, noise_correlation_time_s=tau if modelled else 0.0,
            bearing_correlated_fraction=fraction))
        f = fuser('independent')
        errors = ar1_errors(rng, times, tau, sigma, fraction)
        phase = rng.uniform(0, 2 * np.pi)
        for k, t in enumerate(times):
            a = phase + 0.15 * t
            pose = np.array([*(m_true + 4.0 * np.array([np.cos(a), np.sin(a)])), a + 2.0])
            stamp = int(round((t + 1.0) * S))
            observer.add_pose(stamp, pose, np.zeros((3, 3)))
            batch, = observer.add_observations([ObservationMessage(
                stamp, {'id': np.array([1]),
                        'bearing': np.array([bearing_to(pose, m_true) + errors[k]])})])
            f.add_partial_observations(VIEWS[0], stamp, batch.partial_observations.columns())
            f.fuse_queued()
        ids, m, P, _, _ = f.snapshot()
        d = m[0] - m_true
        nees.append(d @ np.linalg.solve(P[0], d))
    anees = np.mean(nees)
    low, high = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    print(f'modelled {modelled}: ANEES {anees:.2f}, interval [{low:.2f}, {high:.2f}]')
    assert (low <= anees <= high) == consistent, anees
    if not consistent:
        assert anees > 3 * high


# --- Persistence -----------------------------------------------------------------------------

def test_waiting_partial_observations_survive_a_restart(tmp_path):
    path = str(tmp_path / 'map.json')
    m = np.array([3.0, 4.0])
    first, second = np.array([0.0, 0.0, 0.1]), np.array([6.0, 0.0, -0.2])
    P_s = np.diag([1e-4, 2e-4, 1e-5])
    f = fuser(map_file=path)
    f.add_partial_observations(VIEWS[0], S, columns(7, BEARING, bearing_to(first, m), first,
                                                    P_s=P_s, R=1e-6, R_bias=4e-6, group=9))
    f.fuse_queued()
    assert len(f.map) == 0 and list(f.partial.waiting) == [7]
    assert f.save()
    with open(path) as stream:
        saved = json.load(stream)['waiting_partial_observations']
    assert len(saved) == 1 and saved[0]['source'] == VIEWS[0] and saved[0]['view_group'] == 9
    again = fuser(map_file=path)
    again.load()
    restored = again.partial.waiting[7][0]
    original = f.partial.waiting[7][0]
    assert (restored.source, restored.stamp_ns, restored.group) == (VIEWS[0], S, 9)
    for name in ('kind', 's', 'P_s', 'y', 'R', 'R_bias', 'range_scale',
                 'range_scale_bearing_limit'):
        np.testing.assert_array_equal(getattr(restored.views, name),
                                      getattr(original.views, name))
    again.add_partial_observations(VIEWS[1], 2 * S,
                                   columns(7, BEARING, bearing_to(second, m), second))
    again.fuse_queued()
    np.testing.assert_allclose(again.snapshot().m[0], m, atol=1e-9)
    assert again.save()
    with open(path) as stream:
        assert 'waiting_partial_observations' not in json.load(stream)   # placed: none waits


@pytest.mark.parametrize('field, value', [
    ('kind', 3), ('variance', -1.0), ('value', 'x'), ('stamp_ns', 1.5), ('id', 2 ** 70),
    ('source', 4), ('sensor_cov_xx', -1.0), ('range_scale_q2', -9.0),
    ('range_scale_bearing_limit', 0.0), ('range_scale_q0', 'x')])
def test_a_bad_waiting_partial_observation_is_quarantined_and_the_map_kept(tmp_path, field, value):
    path = str(tmp_path / 'map.json')
    f = fuser(map_file=path)
    f.add_landmarks(LANDMARKS[0], LandmarkMessage(S, np.array([1]), np.array([[1.0, 2.0]]),
                    np.eye(2)[None] * 0.01, np.zeros((1, 2, 2))))
    f.add_partial_observations(VIEWS[0], S, columns(7, BEARING, 0.3, [0.0, 0.0, 0.0]))
    f.fuse_queued()
    assert f.save()
    with open(path) as stream:
        document = json.load(stream)
    document['waiting_partial_observations'][0][field] = value
    with open(path, 'w') as stream:
        json.dump(document, stream)
    again = fuser(map_file=path, min_observations=1)
    again.load()
    assert len(again.map) == len(document['landmarks']) and not again.partial.waiting
    assert again.counters['map_records_rejected'] == 1
    assert again.counters['map_file_rejected'] == 0
    assert len(list(tmp_path.glob('map.json.quarantine-*'))) == 1


class _Warnings:

    def __init__(self):
        self.lines = []

    def info(self, text):
        pass

    def warning(self, text):
        self.lines.append(text)

    def error(self, text):
        self.lines.append(text)


def _saved_with_a_waiting_observation(path):
    """Save a map file with one waiting partial observation; return its document."""
    f = fuser(map_file=path)
    f.add_partial_observations(VIEWS[0], S, columns(7, BEARING, 0.3, [0.0, 0.0, 0.0]))
    f.fuse_queued()
    assert f.save()
    with open(path) as stream:
        return json.load(stream)


def test_a_map_file_with_the_deprecated_waiting_views_key_loads_with_a_warning(tmp_path):
    path = str(tmp_path / 'map.json')
    document = _saved_with_a_waiting_observation(path)
    document['waiting_views'] = document.pop('waiting_partial_observations')
    with open(path, 'w') as stream:
        json.dump(document, stream)
    log = _Warnings()
    again = Fuser(FuserConfig(map_file=path), LANDMARKS, log, partial_sources=VIEWS)
    again.load()
    assert list(again.partial.waiting) == [7]
    assert any("'waiting_views' is deprecated" in line for line in log.lines), log.lines
    assert again.save()                       # the next save writes the new key only
    with open(path) as stream:
        saved = json.load(stream)
    assert 'waiting_views' not in saved and len(saved['waiting_partial_observations']) == 1


def test_a_map_file_with_both_waiting_keys_quarantines_the_waiting_section(tmp_path):
    path = str(tmp_path / 'map.json')
    document = _saved_with_a_waiting_observation(path)
    document['waiting_views'] = document['waiting_partial_observations']
    with open(path, 'w') as stream:
        json.dump(document, stream)
    again = fuser(map_file=path)
    again.load()
    assert not again.partial.waiting and again.counters['map_records_rejected'] == 1
    assert again.counters['map_file_rejected'] == 0
    assert len(again.map) == len(document['landmarks'])
    assert len(list(tmp_path.glob('map.json.quarantine-*'))) == 1


def test_the_deprecated_constraint_topics_parameter_still_names_the_partial_sources():
    old = ('/r1/landmark_constraints', '/r2/landmark_constraints')
    config = FuserConfig(constraint_topics=old)
    assert config.partial_observation_topics == old
    log = _Warnings()
    Fuser(config, LANDMARKS, log, partial_sources=list(old))
    assert len(log.lines) == 1 and 'constraint_topics is deprecated' in log.lines[0]
    assert FuserConfig().deprecations() == ()
    assert FuserConfig().partial_observation_topics == ('partial_observations',)
    with pytest.raises(ValueError, match='set only partial_observation_topics'):
        FuserConfig(constraint_topics=old, partial_observation_topics=('/r1/x',))
    # The same topics under both names is no conflict.
    assert FuserConfig(constraint_topics=old,
                       partial_observation_topics=old).partial_observation_topics == old


@pytest.mark.parametrize('ratio, expected', [(0.5, 0.5), (2.0, 2.0), (0.0, None)])
def test_the_fusers_curvature_rule_is_a_parameter(ratio, expected):
    # max_curvature_ratio reaches the placement; 0 turns the rule off (None).
    assert fuser(max_curvature_ratio=ratio).partial.params.max_curvature_ratio == expected


def test_a_map_file_without_range_scale_columns_loads_views_without_one(tmp_path):
    path = str(tmp_path / 'map.json')
    document = _saved_with_a_waiting_observation(path)
    for record in document['waiting_partial_observations']:
        for name in RANGE_SCALE_COLUMNS:
            del record[name]
    with open(path, 'w') as stream:
        json.dump(document, stream)
    again = fuser(map_file=path)
    again.load()
    views = again.partial.waiting[7][0].views
    np.testing.assert_array_equal(views.range_scale, [[0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(views.range_scale_bearing_limit, [np.pi])
