"""The track score: increments, thresholds, online estimators, persistence (fuser.track_score)."""

import json

from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fuser.track_score import (hit_increments, miss_increment, SourceStatistics,
                                            sprt_thresholds, start_score,
                                            team_detection_probability)
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
import pytest
from scipy import stats

S = 1_000_000_000
SOURCE = '/robot1/landmarks'


def test_hit_increment_is_the_log_ratio_of_detection_density_to_clutter_density():
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = rng.normal(size=(2, 2))
        S_ = A @ A.T + 0.05 * np.eye(2)
        m, z = rng.normal(size=2), rng.normal(size=2)
        P_D, density = rng.uniform(0.1, 0.95), rng.uniform(1e-4, 1.0)
        # H1: detected (P_D) at density N(z; m, S); H0: a clutter row, density lambda.
        want = np.log(P_D) + stats.multivariate_normal(m, S_).logpdf(z) - np.log(density)
        got = hit_increments(z[None], m[None], S_[None], P_D, density)
        assert got.shape == (1,) and got[0] == pytest.approx(want, abs=1e-10)


def test_hit_increment_by_hand():
    # S = diag(0.04, 0.01), nu = (0.2, 0.1): d^2 = 1 + 1 = 2; |2 pi S| = (2 pi)^2 4e-4.
    got = hit_increments(np.array([[1.2, 0.1]]), np.array([[1.0, 0.0]]),
                         np.diag([0.04, 0.01])[None], 0.5, 0.01)[0]
    hand = np.log(0.5 / 0.01) - 0.5 * (2.0 + np.log((2 * np.pi) ** 2 * 4e-4))
    assert got == pytest.approx(hand, abs=1e-12) and got == pytest.approx(4.9862, abs=1e-4)


def test_miss_increment_and_wald_thresholds():
    assert miss_increment(0.9) == pytest.approx(np.log(0.1))
    confirm, delete = sprt_thresholds(1e-4, 0.01)
    assert confirm == pytest.approx(np.log(0.99 / 1e-4))
    assert delete == pytest.approx(np.log(0.01 / (1 - 1e-4)))
    for alpha, beta in [(0.0, 0.1), (0.6, 0.5), (0.1, 1.0)]:
        with pytest.raises(ValueError):
            sprt_thresholds(alpha, beta)


def test_start_score_is_the_bounded_log_odds_of_past_tracks():
    assert start_score(0, 0) == 0.0
    assert start_score(9, 99) == pytest.approx(np.log(0.1))
    assert start_score(0, 10 ** 6) == pytest.approx(np.log(1e-3))
    assert start_score(50, 0) == 0.0


def _run(rng, messages, P_D, clutter_rate, radius=5.0):
    """Run a robot at the origin seeing 6 landmarks at ``radius`` [m] with ``P_D``, and clutter."""
    angles = np.linspace(0.0, 2 * np.pi, 6, endpoint=False)
    truth = radius * np.column_stack([np.cos(angles), np.sin(angles)])
    fuser = Fuser(FuserConfig(), [SOURCE])
    scan = Scan(np.zeros(2), np.zeros((3, 3)))
    R = 0.0025 * np.eye(2)
    for k in range(messages):
        seen = truth[rng.random(len(truth)) < P_D]
        seen = seen + rng.normal(0.0, 0.05, seen.shape)
        count = rng.poisson(clutter_rate)
        r, a = radius * np.sqrt(rng.random(count)), rng.uniform(-np.pi, np.pi, count)
        z = np.concatenate([seen, np.column_stack([r * np.cos(a), r * np.sin(a)])])
        if not len(z):
            continue
        P = np.broadcast_to(R, (len(z), 2, 2)).copy()
        fuser.add_landmarks(SOURCE, LandmarkMessage((k + 1) * S, [UNKNOWN_ID] * len(z), z, P,
                                                    0.0 * P, scan=scan))
        fuser.fuse_queued()
    return fuser, truth


def test_online_estimates_converge_to_the_simulated_clutter_density_and_p_D():
    fuser, truth = _run(np.random.default_rng(7), 1500, 0.7, 2.0)
    estimates = fuser.tracker.statistics[SOURCE]
    assert estimates.range_m == pytest.approx(5.0, abs=0.2)
    # 2 rows per message over the disc of radius 5 m.
    assert estimates.clutter_density == pytest.approx(2.0 / (np.pi * 25.0), rel=0.1)
    assert estimates.detection_probability == pytest.approx(0.7, abs=0.03)
    ids, m = fuser.snapshot()[:2]
    assert len(ids) == len(truth)     # the six landmarks, no clutter track


def _run_field_of_view(rng, messages, P_D, clutter_rate, heading_known, half=0.6):
    """
    Run a robot at the origin turning at random, 12 landmarks 5 m around it.

    The sensor sees those within ``half`` [rad] of its heading, each with ``P_D``, and a
    Poisson number of clutter rows uniform over that sector; the messages carry the
    heading when ``heading_known``.
    """
    angles = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    truth = 5.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    fuser = Fuser(FuserConfig(), [SOURCE])
    R = 0.0025 * np.eye(2)
    for k in range(messages):
        heading = rng.uniform(-np.pi, np.pi)
        bearing = (angles - heading + np.pi) % (2 * np.pi) - np.pi
        seen = truth[(np.abs(bearing) <= half) & (rng.random(len(truth)) < P_D)]
        seen = seen + rng.normal(0.0, 0.05, seen.shape)
        count = rng.poisson(clutter_rate)
        r, a = 5.0 * np.sqrt(rng.random(count)), heading + rng.uniform(-half, half, count)
        z = np.concatenate([seen, np.column_stack([r * np.cos(a), r * np.sin(a)])])
        if not len(z):
            continue
        P = np.broadcast_to(R, (len(z), 2, 2)).copy()
        scan = Scan(np.zeros(2), np.zeros((3, 3)), heading=heading if heading_known else None)
        fuser.add_landmarks(SOURCE, LandmarkMessage((k + 1) * S, [UNKNOWN_ID] * len(z), z, P,
                                                    0.0 * P, scan=scan))
        fuser.fuse_queued()
    return fuser, truth


def test_the_field_of_view_is_estimated_and_p_D_counts_only_landmarks_in_it():
    fuser, truth = _run_field_of_view(np.random.default_rng(3), 1500, 0.8, 1.0, True)
    estimates = fuser.tracker.statistics[SOURCE]
    assert estimates.half_view_rad == pytest.approx(0.6, abs=0.05) and estimates.paired_view
    assert estimates.detection_probability == pytest.approx(0.8, abs=0.03)
    # One row per message over the sector of half-angle 0.6 rad and radius 5 m.
    assert estimates.clutter_density == pytest.approx(1.0 / (0.6 * 25.0), rel=0.15)
    assert len(fuser.snapshot().ids) == len(truth)
    # Without the heading the view is the disc: the landmarks behind the robot count as
    # missed and P_D is diluted to about the share of the circle the sector covers.
    disc, _ = _run_field_of_view(np.random.default_rng(3), 1500, 0.8, 1.0, False)
    diluted = disc.tracker.statistics[SOURCE]
    assert diluted.half_view_rad == 0.0 and not diluted.paired_view
    assert diluted.detection_probability < 0.3


def test_view_membership_area_and_the_team_estimate():
    stats = SourceStatistics()
    stats.see(np.array([2.0, 4.0]), np.array([False, False]), np.array([0.3, -0.5]))
    assert (stats.range_m, stats.half_view_rad, stats.paired_view) == (4.0, 0.5, False)
    # Before a row went to a confirmed landmark the view is the disc.
    assert stats.view_area(0.0) == pytest.approx(np.pi * 16.0)
    assert stats.in_view(np.array([[-3.0, 0.0]]), np.zeros(2), 0.0).tolist() == [True]
    # Rows paired with confirmed landmarks replace the bounds of unpaired rows, then widen.
    stats.see(np.array([3.0, 1.0]), np.array([True, False]), np.array([0.2, 1.0]))
    assert (stats.range_m, stats.half_view_rad, stats.paired_view) == (3.0, 0.2, True)
    stats.see(np.array([3.5]), np.array([True]), np.array([-0.4]))
    assert (stats.range_m, stats.half_view_rad) == (3.5, 0.4)
    stats.see(np.array([9.0]), np.array([True]))        # no heading: the view's angle stays
    assert (stats.range_m, stats.half_view_rad) == (9.0, 0.4)
    assert stats.view_area(0.0) == pytest.approx(0.4 * 81.0)
    assert stats.view_area(None) == pytest.approx(np.pi * 81.0)
    robot, heading = np.array([1.0, 1.0]), np.pi - 0.1
    xy = robot + np.array([[-5.0, 0.0], [-5.0, 5.0 * np.tan(0.6)], [5.0, 0.0], [-9.5, 0.0],
                           [0.0, -1.0]])
    np.testing.assert_array_equal(stats.in_view(xy, robot, heading),
                                  [True, False, False, False, False])
    np.testing.assert_array_equal(stats.in_view(xy, robot, None),
                                  [True, True, True, False, True])
    assert team_detection_probability([]) is None
    assert team_detection_probability([SourceStatistics()]) is None
    assert team_detection_probability([SourceStatistics(expected=8, detected=8),
                                       SourceStatistics(expected=90, detected=9)]) == (
        pytest.approx(18.0 / 100.0))
    assert team_detection_probability([SourceStatistics(expected=1000, detected=1000)]) == 0.99
    back = SourceStatistics.from_dict(json.loads(json.dumps(stats.to_dict())))
    assert back == stats


def test_statistics_and_scores_survive_a_restart_and_older_files_load(tmp_path):
    path = str(tmp_path / 'map.json')
    fuser, _ = _run(np.random.default_rng(1), 60, 0.7, 2.0)
    fuser.config = FuserConfig(map_file=path)
    assert fuser.tracker.tentative and fuser.save()
    again = Fuser(FuserConfig(map_file=path), [SOURCE])
    again.load()
    assert again.tracker.statistics == fuser.tracker.statistics
    for landmark_id, track in fuser.tracker.tentative.items():
        resumed = again.tracker.tentative[landmark_id]
        assert resumed.score == pytest.approx(track.score)
        assert (resumed.released, resumed.hits) == (track.released, track.hits)
        np.testing.assert_allclose(resumed.m, track.m, atol=1e-12)
    # A file written before the scores: no statistics, tracks without score fields.
    with open(path) as stream:
        document = json.load(stream)
    del document['tracks']['statistics']
    for entry in document['tracks']['tentative']:
        for key in ('score', 'released', 'hits'):
            del entry[key]
    with open(path, 'w') as stream:
        json.dump(document, stream)
    old = Fuser(FuserConfig(map_file=path), [SOURCE])
    old.load()
    assert old.tracker.statistics == {}
    assert set(old.tracker.tentative) == set(fuser.tracker.tentative)
    assert all(t.released and t.score == 0.0 for t in old.tracker.tentative.values())


@pytest.mark.parametrize('document', [{'range_m': -1.0}, {'expected': 'x'},
                                      {'paired_range': 1}, {'area': float('nan')}])
def test_bad_statistics_are_refused(document):
    with pytest.raises(ValueError):
        SourceStatistics.from_dict(document)


def test_clutter_tracks_are_deleted_by_their_misses_not_confirmed():
    # Clutter only: every track dies by its score; no landmark is confirmed.
    fuser, _ = _run(np.random.default_rng(5), 300, 0.0, 3.0)
    counts = fuser.sources[SOURCE].counts
    assert len(fuser.snapshot()[0]) == 0 and counts['confirmed'] == 0
    assert counts['deleted'] >= 0.9 * counts['new_tentative']
