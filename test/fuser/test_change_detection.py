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
from landmark_ros.fusion.records import Observation
from landmark_ros.pipeline.config import FuserConfig
import numpy as np
import pytest
from scipy import stats

CLIP = chi2_threshold(2, 0.999)
SOURCES = ['/robot1/landmarks', '/robot2/landmarks', '/robot3/landmarks']
RATE = 2e-5
"""The false-alarm rate the tests switch detection on with (the default)."""


def test_increment_is_the_log_likelihood_ratio():
    x = np.linspace(0.0, 30.0, 61)
    for lam in (1.0, 3.0, 9.0):
        expected = stats.ncx2.logpdf(x[1:], 2, lam) - stats.chi2.logpdf(x[1:], 2)
        np.testing.assert_allclose(increment(x[1:], lam), expected, rtol=1e-9, atol=1e-9)
        assert increment(np.array([0.0]), lam)[0] == pytest.approx(-lam / 2)


@pytest.mark.parametrize('clip', [CLIP, 6.0])
def test_average_run_length_matches_a_simulation(clip):
    """ARL0 of a small threshold against the mean run length of simulated tests."""
    rng = np.random.default_rng(3)
    h, lam = (3.0 if clip == CLIP else 1.5), 3.0   # ARL0 about 150 either way
    arl = average_run_length(h, lam, clip)
    runs, statistic, steps = [], np.zeros(4000), np.zeros(4000, int)
    for _ in range(4000):
        statistic = np.maximum(0.0, statistic + increment(np.minimum(
            rng.chisquare(2, 4000), clip), lam))
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


def test_on_by_default_and_off_when_rate_is_zero():
    rng = np.random.default_rng(11)
    truth = np.array([[0.0, 0.0]])
    assert FuserConfig().move_false_alarm_rate == 2e-5       # on by default
    assert FuserConfig().move_min_sources == 2
    assert Fuser(FuserConfig(), SOURCES).moves is not None
    fuser = Fuser(FuserConfig(move_false_alarm_rate=0.0), SOURCES)
    assert fuser.moves is None
    stamp = _feed(fuser, rng, truth, 30, 1_000_000_000)
    truth[0] += [0.25, 0.0]
    _feed(fuser, rng, truth, 10, stamp)
    assert fuser.counters['landmark_moved'] == 0
    with pytest.raises(ValueError):
        FuserConfig(move_false_alarm_rate=1e-13)


def test_mutation_rebuild_from_all_rows_fails(monkeypatch):
    """Mutation check: a rebuild from every row (not the post-change ones) is caught."""
    original = change_detection.MoveDetector.observe
    history = {}

    def from_everything(self, ids, d2, rows, names=None, groups=None):
        alarms = original(self, ids, d2, rows, names, groups)
        z, R_ind, R_dep, sources, stamps = rows
        for k, landmark_id in enumerate(ids.tolist()):
            source = sources[k] if names is None else names[sources[k]]
            history.setdefault(landmark_id, []).append(
                Observation(z[k], R_ind[k], R_dep[k], str(source), int(stamps[k])))
        return [alarm._replace(observations=history[alarm.landmark_id]) for alarm in alarms]

    monkeypatch.setattr(change_detection.MoveDetector, 'observe', from_everything)
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


def _page(d2, h, lam):
    """Page's test row by row (the textbook recursion); return the rows that raised alarms."""
    C, alarms = 0.0, []
    for k, g in enumerate(increment(np.minimum(d2, CLIP), lam)):
        C = max(0.0, C + g)
        if C >= h:
            alarms.append(k)
            C = 0.0
    return alarms


def test_one_source_is_pages_test():
    """min_sources 1: the same alarms as Page's recursion, whatever the sources."""
    rng = np.random.default_rng(8)
    d2 = rng.noncentral_chisquare(2, 1.5, 2000)
    detector = MoveDetector(1e-3, 1.75, CLIP, min_sources=1)
    ids = np.zeros(2000, np.int64)
    rows = _rows(ids, np.zeros((2000, 2)))
    rows = rows[:3] + (np.array(SOURCES)[rng.integers(0, 3, 2000)], rows[4])
    got = []
    for k in range(2000):
        if detector.observe(ids[k:k + 1], d2[k:k + 1], tuple(r[k:k + 1] for r in rows)):
            got.append(k)
    want = _page(d2, detector.threshold, detector.noncentrality)
    assert len(want) > 20 and got == want


def test_one_source_alone_cannot_raise_an_alarm():
    """min_sources 2: one source's evidence counts up to h / 2, however much it has."""
    detector = MoveDetector(1e-4, 1.75, CLIP, min_sources=2)
    ids = np.zeros(200, np.int64)
    d2 = np.full(200, CLIP)
    assert detector.observe(ids, d2, _rows(ids, np.zeros((200, 2)))) == []
    assert detector.statistic[0] == pytest.approx(detector.threshold / 2, rel=1e-12)
    # A second source: its own evidence adds until it reaches h / 2 as well.
    g = increment(np.array([CLIP]), detector.noncentrality)[0]
    needed = int(np.ceil(detector.threshold / 2 / g))
    rows = _rows(ids[:needed], np.zeros((needed, 2)))
    rows = rows[:3] + (['b'] * needed, rows[4])
    alarms = detector.observe(ids[:needed], d2[:needed], rows)
    assert len(alarms) == 1 and detector.alarms[0] == 1
    # Its post-change rows: every row of the run, both sources (the last 64).
    assert len(alarms[0].observations) == change_detection.MAX_POST_CHANGE_ROWS
    with pytest.raises(ValueError):
        MoveDetector(1e-4, 1.75, CLIP, min_sources=0)


def test_the_statistic_sums_the_capped_evidence_of_each_source():
    detector = MoveDetector(1e-6, 1.75, CLIP, min_sources=2)
    d2 = np.array([CLIP, CLIP, CLIP, 9.0, 0.5, CLIP])
    sources = np.array(['a', 'a', 'a', 'b', 'b', 'a'])
    ids = np.zeros(6, np.int64)
    rows = _rows(ids, np.zeros((6, 2)))
    assert detector.observe(ids, d2, rows[:3] + (sources, rows[4])) == []
    g = increment(np.minimum(d2, CLIP), detector.noncentrality)
    a, b = g[sources == 'a'].sum(), g[sources == 'b'].sum()
    assert a > detector.cap > b > 0.0
    assert detector.statistic[0] == pytest.approx(detector.cap + b, rel=1e-12)


def test_capping_keeps_the_false_alarm_rate_under_the_design():
    """
    Static rows of three interleaved sources: fewer alarms than Page's test.

    The capped statistic never exceeds Page's started at the same row, so its run
    lengths are at least Page's and its rate at most the design's.
    """
    rng = np.random.default_rng(4)
    detector = MoveDetector(1e-2, 1.75, CLIP, min_sources=2)
    arl = average_run_length(detector.threshold, detector.noncentrality, CLIP)
    n = 200_000
    ids = np.zeros(n, np.int64)
    d2 = rng.chisquare(2, n)
    rows = _rows(ids, np.zeros((n, 2)))
    sources = np.array(SOURCES)[np.arange(n) % 3]
    alarms = 0
    for k in range(0, n, 500):
        alarms += len(detector.observe(ids[k:k + 500], d2[k:k + 500], tuple(
            r[k:k + 500] for r in rows[:3]) + (sources[k:k + 500], rows[4][k:k + 500])))
    page = len(_page(d2, detector.threshold, detector.noncentrality))
    assert page == pytest.approx(n / arl, rel=0.15)      # the design rate, about 2,000
    assert alarms < 0.5 * page


@pytest.mark.parametrize('min_sources', [1, 2])
def test_one_robots_persistent_error_is_not_a_move(min_sources):
    """
    One robot's persistent error on a landmark is not a move.

    That robot sees landmark 0 shifted 0.25 m for 30 messages; the others see it where
    it is. With two sources needed (the default) no alarm; with one source the same
    rows raise one (the shift is not too small to see). The same shift seen by every
    robot is a move (the test above).
    """
    rng = np.random.default_rng(13)
    truth = np.array([[0.0, 0.0], [5.0, 5.0]])
    config = FuserConfig(move_false_alarm_rate=RATE, move_min_sources=min_sources)
    fuser = Fuser(config, SOURCES)
    stamp = _feed(fuser, rng, truth, 60, 1_000_000_000)
    ids = np.arange(2, dtype=np.int64)
    for _ in range(30):
        for source in SOURCES:
            seen = truth + ([[0.25, 0.0], [0.0, 0.0]] if source == SOURCES[0] else 0.0)
            m, P, P_dep = moved_landmark.draw_rows(rng, seen)
            fuser.add_landmarks(source, LandmarkMessage(stamp, ids, m, P, P_dep))
            fuser.fuse_queued()
            stamp += 10_000_000
    assert (fuser.moves.alarms[0] > 0) == (min_sources == 1)
    assert fuser.moves.alarms[1] == 0


@pytest.mark.parametrize('min_sources, batch', [(1, 7), (2, 1), (2, 13), (3, 50)])
def test_the_vectorised_batch_equals_the_row_by_row_loop(monkeypatch, min_sources, batch):
    """Closed form for the landmarks under the cap, the loop for the rest: same tests."""
    rng = np.random.default_rng(min_sources * 100 + batch)
    n = 3000
    ids = rng.integers(0, 6, n)
    sources = np.array(SOURCES)[rng.integers(0, 3, n)]
    # Static rows, then from row 1500 landmark 0 seen shifted by every source and
    # landmark 1 by the first source only: alarms and sources above the cap.
    shift = np.where((np.arange(n) > 1500) & ((ids == 0) | ((ids == 1) & (sources == SOURCES[0]))),
                     3.0, 0.0)
    d2 = rng.noncentral_chisquare(2, 0.01 + shift, n)
    d2[rng.random(n) < 0.2] = np.nan                     # rows not tested
    rows = _rows(ids, rng.standard_normal((n, 2)))
    rows = rows[:3] + (sources, rows[4])

    def run(detector):
        alarms = []
        for k in range(0, n, batch):
            part = slice(k, k + batch)
            alarms += [(a.landmark_id, [o.stamp_ns for o in a.observations])
                       for a in detector.observe(ids[part], d2[part],
                                                 tuple(r[part] for r in rows))]
        return alarms, detector
    fast, fast_detector = run(MoveDetector(1e-3, 1.75, CLIP, min_sources=min_sources))
    with monkeypatch.context() as patch:
        patch.setattr(MoveDetector, '_fast', lambda self, landmarks, *rest: np.ones(
            len(landmarks), bool))
        slow, slow_detector = run(MoveDetector(1e-3, 1.75, CLIP, min_sources=min_sources))
    assert len(slow) >= 3 and fast == slow
    assert fast_detector.statistic.keys() == slow_detector.statistic.keys()
    for key, value in slow_detector.statistic.items():
        assert fast_detector.statistic[key] == pytest.approx(value, rel=1e-9, abs=1e-9)
    assert fast_detector.tested == slow_detector.tested
