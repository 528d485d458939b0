"""Change detection: Page's test on the innovations, its threshold and the rebuild."""

from dataclasses import replace

from landmark_ros.core.gating import chi2_threshold
from landmark_ros.eval import moved_landmark
from landmark_ros.fuser import change_detection
from landmark_ros.fuser.change_detection import (average_run_length, increment, MoveDetector,
                                                 threshold_for)
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.pipeline.config import FuserConfig
import numpy as np
import pytest
from scipy import stats

CLIP = chi2_threshold(2, 0.999)
SOURCES = ['/robot1/landmarks', '/robot2/landmarks', '/robot3/landmarks']
RATE = 2e-5
"""The false-alarm rate the tests switch detection on with (off by default)."""


def test_increment_is_the_log_likelihood_ratio():
    x = np.linspace(0.0, 30.0, 61)
    for lam in (1.0, 3.0, 9.0):
        expected = stats.ncx2.logpdf(x[1:], 2, lam) - stats.chi2.logpdf(x[1:], 2)
        np.testing.assert_allclose(increment(x[1:], lam), expected, rtol=1e-9, atol=1e-9)
        assert increment(np.array([0.0]), lam)[0] == pytest.approx(-lam / 2)


def test_average_run_length_matches_a_simulation():
    """ARL0 of a small threshold against the mean run length of simulated tests."""
    rng = np.random.default_rng(3)
    h, lam = 3.0, 3.0
    arl = average_run_length(h, lam, CLIP)
    runs, statistic, steps = [], np.zeros(4000), np.zeros(4000, int)
    for _ in range(4000):
        statistic = np.maximum(0.0, statistic + increment(np.minimum(
            rng.chisquare(2, 4000), CLIP), lam))
        steps += 1
        over = statistic > h
        runs += steps[over].tolist()
        statistic[over], steps[over] = 0.0, 0
    assert np.mean(runs) == pytest.approx(arl, rel=0.05)


def test_threshold_gives_the_rate():
    h = threshold_for(1e-4, 3.0, CLIP)
    assert average_run_length(h, 3.0, CLIP) == pytest.approx(1e4, rel=1e-4)
    assert threshold_for(1e-5, 3.0, CLIP) > h
    with pytest.raises(ValueError):
        threshold_for(0.0, 3.0, CLIP)


def _rows(ids, z):
    n = len(ids)
    R = np.broadcast_to(0.01 * np.eye(2), (n, 2, 2)).copy()
    return (z, R, np.zeros_like(R), ['a'] * n, np.arange(n, dtype=np.int64))


def test_detector_keeps_post_change_rows_only():
    """The rows before the last zero of the statistic are not in the alarm."""
    detector = MoveDetector(1e-4, 1.75, CLIP)
    ids = np.zeros(12, np.int64)
    d2 = np.array([0.1, 0.2, 0.1, 0.3] + [CLIP] * 8)
    z = np.arange(24, dtype=float).reshape(12, 2)
    alarms = detector.observe(ids, d2, _rows(ids, z))
    assert len(alarms) == 1 and alarms[0].landmark_id == 0
    assert [obs.stamp_ns for obs in alarms[0].observations] == list(range(4, 12))
    assert detector.alarms[0] == 1 and 0 not in detector.statistic


def test_detector_carries_its_state_across_batches():
    """
    Row by row and all at once: the same first alarms and post-change rows.

    In one batch the rows after the alarm are post-change rows too (they are fused
    already); row by row the alarm takes the rows up to it.
    """
    rng = np.random.default_rng(5)
    ids = rng.integers(0, 3, 300)
    d2 = rng.chisquare(2, 300) * np.where(np.arange(300) > 150, 4.0, 1.0)
    z = rng.standard_normal((300, 2))
    whole = MoveDetector(1e-3, 1.75, CLIP)
    one = MoveDetector(1e-3, 1.75, CLIP)
    rows = _rows(ids, z)
    expected = [(a.landmark_id, [o.stamp_ns for o in a.observations])
                for a in whole.observe(ids, d2, rows)]
    got = []
    for i in range(300):
        got += [(a.landmark_id, [o.stamp_ns for o in a.observations]) for a in one.observe(
            ids[i:i + 1], d2[i:i + 1], tuple(column[i:i + 1] for column in rows[:3])
            + (rows[3][i:i + 1], rows[4][i:i + 1]))]
    assert len(expected) == 3
    for landmark_id, stamps in expected:
        first = next(kept for key, kept in got if key == landmark_id)
        assert first and stamps[:len(first)] == first


def _feed(fuser, rng, truth, steps, stamp):
    """Send ``steps`` messages per source, one row per landmark; return the next stamp."""
    ids = np.arange(len(truth), dtype=np.int64)
    for _ in range(steps):
        for source in SOURCES:
            m, P, P_dep = moved_landmark.draw_rows(rng, truth)
            fuser.add_landmarks(source, LandmarkMessage(stamp, ids, m, P, P_dep))
            fuser.fuse_queued()
            stamp += 10_000_000
    return stamp


@pytest.mark.parametrize('fusion', FUSION_METHODS)
def test_a_moved_landmark_is_rebuilt_from_post_change_rows(fusion):
    rng = np.random.default_rng(11)
    truth = np.array([[0.0, 0.0], [5.0, 5.0]])
    fuser = Fuser(FuserConfig(fusion=fusion, move_false_alarm_rate=RATE), SOURCES)
    stamp = _feed(fuser, rng, truth, 60, 1_000_000_000)
    assert fuser.counters['landmark_moved'] == 0
    moved_at = stamp
    truth[0] += [0.25, 0.0]
    _feed(fuser, rng, truth, 10, stamp)
    assert fuser.counters['landmark_moved'] == 1
    assert fuser.moves.alarms[0] == 1 and fuser.moves.alarms[1] == 0
    records = {record['id']: record for record in fuser.map.to_records()}
    assert records[0]['first_stamp_ns'] == 1_000_000_000
    m, P, _ = fuser.map.estimate(0)
    # Rebuilt from rows after the move (Page's change point may take a row or two
    # before it), not the 180 before: no pull towards the old position.
    assert records[0]['observations'] <= 36
    assert np.linalg.norm(m - truth[0]) < 0.1
    status = fuser.statuses(stamp)[0]
    assert status.counts['landmark_moved'] == 1
    assert moved_at > 0


def test_split_ci_sums_restart_from_the_post_change_rows():
    """The per-source sums hold the post-change rows, not those before the move."""
    information = []
    for rate in (2e-5, 0.0):
        rng = np.random.default_rng(2)
        truth = np.array([[0.0, 0.0]])
        fuser = Fuser(FuserConfig(move_false_alarm_rate=rate), SOURCES)
        stamp = _feed(fuser, rng, truth, 40, 1_000_000_000)
        truth[0] += [0.0, 0.3]
        _feed(fuser, rng, truth, 10, stamp)
        assert fuser.counters['landmark_moved'] == (1 if rate else 0)
        per_source = fuser.map.to_records()[0]['per_source']
        assert len(per_source) == 3
        information.append(sum(np.trace(entry['information']) for entry in per_source))
    # About 30 of 150 rows: well under half the information of all of them.
    assert information[0] < 0.4 * information[1]


def test_no_false_alarm_on_a_long_static_run():
    """20 landmarks x 3 sources x 200 messages: 12,000 static rows, seeded."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(-10.0, 10.0, (20, 2))
    for fusion in FUSION_METHODS:
        fuser = Fuser(FuserConfig(fusion=fusion, move_false_alarm_rate=RATE), SOURCES)
        _feed(fuser, rng, truth, 200, 1_000_000_000)
        assert sum(fuser.moves.alarms.values()) == 0, fusion
        assert fuser.counters['landmark_moved'] == 0


def test_off_when_rate_is_zero():
    rng = np.random.default_rng(11)
    truth = np.array([[0.0, 0.0]])
    fuser = Fuser(FuserConfig(move_false_alarm_rate=0.0), SOURCES)
    assert fuser.moves is None
    stamp = _feed(fuser, rng, truth, 30, 1_000_000_000)
    truth[0] += [0.25, 0.0]
    _feed(fuser, rng, truth, 10, stamp)
    assert fuser.counters['landmark_moved'] == 0
    with pytest.raises(ValueError):
        FuserConfig(move_false_alarm_rate=1e-13)


def test_mutation_rebuild_from_all_rows_fails(monkeypatch):
    """Mutation check: a rebuild from every kept row (not the post-change ones) is caught."""
    original = change_detection.MoveDetector._close

    def from_everything(self, landmark_id, statistic, positions, rows):
        alarm = original(self, landmark_id, statistic, positions, rows)
        if alarm is not None:
            return alarm._replace(observations=self.history.get(landmark_id, [])
                                  + alarm.observations)
        self.history.setdefault(landmark_id, []).extend(
            change_detection._observations(positions, rows))
        return alarm

    monkeypatch.setattr(change_detection.MoveDetector, '_close', from_everything)
    monkeypatch.setattr(change_detection.MoveDetector, 'history', {}, raising=False)
    rng = np.random.default_rng(11)
    truth = np.array([[0.0, 0.0], [5.0, 5.0]])
    fuser = Fuser(replace(FuserConfig(move_false_alarm_rate=RATE), fusion='independent'), SOURCES)
    stamp = _feed(fuser, rng, truth, 60, 1_000_000_000)
    truth[0] += [0.25, 0.0]
    _feed(fuser, rng, truth, 10, stamp)
    m, _, _ = fuser.map.estimate(0)
    # The test above asserts < 0.1 m: this mutant is pulled back to the old position.
    assert fuser.counters['landmark_moved'] == 0 or np.linalg.norm(m - truth[0]) >= 0.1


def test_the_statistic_accumulates_the_clipped_increments_and_counts_the_rows():
    detector = MoveDetector(1e-6, 1.75, CLIP)
    ids = np.zeros(4, np.int64)
    d2 = np.array([8.0, 9.0, 2 * CLIP, 10.0])
    assert detector.observe(ids, d2, _rows(ids, np.zeros((4, 2)))) == []
    want = np.sum(increment(np.minimum(d2, CLIP), 1.75 ** 2))
    assert detector.statistic[0] == pytest.approx(want, rel=1e-12) and detector.tested == 4
