"""Merging the tracks of landmarks without IDs: the co-occurrence test (fuser.tracks)."""

from collections import Counter
import json

from landmark_ros.core.gating import chi2_threshold, difference_mahalanobis_sq
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fuser.track_score import (one_landmark_by_sightings, SourceStatistics,
                                            sprt_thresholds)
from landmark_ros.fuser.tracks import together_log_likelihood_ratio
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
import pytest
from scipy import stats

S = 1_000_000_000
SOURCE = '/robot1/landmarks'
CERTAIN = Scan(np.zeros(2), np.zeros((3, 3)))
EAGER = {'false_track_probability': 0.49}
"""A score test that confirms a track on its second row (``min_observations`` decides)."""


@pytest.mark.parametrize('k, n, same, distinct', [
    (0, 0, 0.01, 0.8), (0, 12, 0.01, 0.8), (1, 40, 0.01, 0.818), (2, 33, 0.05, 0.2),
    (7, 9, 0.001, 0.5), (30, 30, 0.2, 0.9)])
def test_together_log_likelihood_ratio_is_the_binomial_ratio(k, n, same, distinct):
    want = stats.binom.logpmf(k, n, same) - stats.binom.logpmf(k, n, distinct)
    assert together_log_likelihood_ratio(k, n, same, distinct) == pytest.approx(want, abs=1e-12)


def _two_confirmed_tracks(config):
    """Return a fuser with two owned confirmed tracks 5 cm apart (compatible), a and b."""
    fuser = Fuser(config, [SOURCE])
    tracker, C = fuser.tracker, np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)).copy()
    a, b = tracker.allocate(fuser.map), tracker.allocate(fuser.map)
    fuser.map.update([a, a, a], np.array([[0.0, 0.0]] * 3), C, 0 * C, 'r', S)
    fuser.map.update([b, b], np.array([[0.05, 0.0]] * 2), C[:2], 0 * C[:2], 'r', S)
    return fuser, a, b


def _sightings(tracker, a, b, alone_a, alone_b, both):
    """Messages that see both, then ``alone_a`` that see a only, ``alone_b`` b only."""
    for ids in [[a, b]] * both + [[a]] * alone_a + [[b]] * alone_b:
        tracker.note_sightings(np.array(ids, np.int64))


ESTIMATED = SourceStatistics(expected=200, detected=180)
"""A source whose messages detected 90 % of the landmarks in their view."""


@pytest.mark.parametrize('p_D, estimate, alone_a, alone_b, both, merged', [
    # A duplicate: once in one message with its landmark's first track (a clutter row
    # beside it), 40 messages saw only one of the two. Merged when p_D is known or
    # estimated.
    (0.9, None, 30, 10, 1, True),
    (0.0, ESTIMATED, 30, 10, 1, True),
    (0.0, None, 30, 10, 1, False),    # no p_D, no estimate: once together, never merged
    # Two landmarks seen together as often as p_D says (0.82 of the messages): apart.
    (0.9, None, 5, 4, 30, False),
    (0.0, ESTIMATED, 5, 4, 30, False),
    # A second track that meets the first in a third of its messages (a close pair whose
    # one track took both landmarks' rows, the other the rows of scans that saw both):
    # "one landmark" does not explain it, whatever p_D says.
    (0.99, None, 10, 0, 5, False),
    # MRCLAM's worst real pair while compatible (19 and 20: 2 of 33 messages): apart.
    (0.0, None, 16, 15, 2, False),
    # Never together: merged, whatever p_D (the rule without co-occurrence).
    (0.0, None, 3, 2, 0, True), (0.9, None, 3, 2, 0, True)])
def test_compatible_tracks_merge_when_their_co_occurrence_says_one_landmark(
        p_D, estimate, alone_a, alone_b, both, merged):
    fuser, a, b = _two_confirmed_tracks(FuserConfig(detection_probability=p_D))
    tracker, counts = fuser.tracker, Counter()
    if estimate is not None:
        tracker.statistics['/robot2/landmarks'] = estimate
    _sightings(tracker, a, b, alone_a, alone_b, both)
    result = tracker.merge(fuser.map, counts)
    if merged:
        assert result == [(b, a)] and counts['merged'] == 1
        assert fuser.snapshot().ids.tolist() == [a] and tracker.resolve(b) == a
        # The merged track was seen in every message that saw either.
        assert tracker.sightings == {a: alone_a + alone_b + both} and tracker.together == {}
    else:
        assert result == [] and counts['merged'] == 0
        assert fuser.snapshot().ids.tolist() == [a, b]


@pytest.mark.parametrize('extra', [{}, EAGER])
def test_the_test_needs_evidence_the_co_occurrence_is_rare(extra):
    # Once together, then messages that saw one of them: merged when the ratio
    # (n - k) log((1 - same) / (1 - q)) - k log(q / same) reaches the confirmation
    # threshold of the track score.
    config = FuserConfig(detection_probability=0.9, **extra)
    confirm, _ = sprt_thresholds(config.false_track_probability,
                                 config.lost_track_probability)
    q = 0.9 / 1.1
    needed = int(np.ceil((confirm + np.log(q / 0.01)) / (np.log(0.99) - np.log(1 - q))))
    fuser, a, b = _two_confirmed_tracks(config)
    _sightings(fuser.tracker, a, b, needed - 1, 0, 1)
    assert fuser.tracker.merge(fuser.map, Counter()) == []
    fuser.tracker.note_sightings(np.array([b]))
    assert fuser.tracker.merge(fuser.map, Counter()) == [(b, a)]


def _duplicate_run(config):
    """
    Feed one landmark at the origin and a clutter row beside it, twice, then the landmark.

    Returns the fuser and its counters. The first two messages confirm track A; two
    messages with a second row 12 cm off (clutter, or a mis-associated row) start and
    confirm track B, seen twice with A; then 30 messages of the landmark alone.
    """
    fuser = Fuser(config, [SOURCE])
    R = 0.01 * np.eye(2)
    rows = [[(0.0, 0.0)], [(0.02, 0.0)], [(0.0, 0.01), (0.12, 0.0)],
            [(0.0, -0.01), (0.11, 0.01)]] + [[(0.01 * (-1) ** k, 0.0)] for k in range(30)]
    for k, message in enumerate(rows):
        m = np.array(message)
        P = np.broadcast_to(R, (len(m), 2, 2)).copy()
        fuser.add_landmarks(SOURCE, LandmarkMessage(
            (k + 1) * S, [UNKNOWN_ID] * len(m), m, P, 0.2 * P, scan=CERTAIN))
        fuser.fuse_queued()
    return fuser, fuser.sources[SOURCE].counts


def test_a_duplicate_started_beside_its_landmark_is_merged_with_p_D_known_or_estimated():
    fuser, counts = _duplicate_run(FuserConfig(detection_probability=0.9, **EAGER))
    assert counts['confirmed'] == 2 and counts['merged'] == 1
    (kept,) = fuser.snapshot().ids.tolist()
    assert fuser.take_removed() == [(kept + 1, kept)]
    # 34 messages; the one that started B is counted for either track and is not a
    # meeting, so the merged count holds it twice (an upper bound of n).
    assert fuser.tracker.sightings == {kept: 35} and fuser.tracker.together == {}
    # The package default: p_D estimated from the messages (the landmark seen in every
    # one of them), merged too.
    fuser, counts = _duplicate_run(FuserConfig(**EAGER))
    assert counts['confirmed'] == 2 and counts['merged'] == 1
    assert fuser.tracker.statistics[SOURCE].detection_probability > 0.9
    assert len(fuser.snapshot().ids) == 1


def test_an_mrclam_like_close_pair_is_never_merged(rng):
    # Two landmarks 18 cm apart (an MRCLAM barcode pair), rows with 8 cm of noise so
    # that young tracks of the two are compatible; each message sees each with
    # probability 0.35 (both in about 20 % of the messages seeing either, as on
    # dataset 6). Package defaults.
    truth = np.array([[2.0, 1.0], [2.18, 1.0]])
    fuser = Fuser(FuserConfig(**EAGER), [SOURCE])
    R = 0.0064 * np.eye(2)
    for k in range(400):
        seen = np.flatnonzero(rng.random(2) < 0.35)
        if not len(seen):
            continue
        m = truth[seen] + rng.normal(0.0, 0.08, (len(seen), 2))
        P = np.broadcast_to(R, (len(m), 2, 2)).copy()
        fuser.add_landmarks(SOURCE, LandmarkMessage(
            (k + 1) * S, [UNKNOWN_ID] * len(m), m, P, 0.2 * P, scan=CERTAIN))
        fuser.fuse_queued()
    counts = fuser.sources[SOURCE].counts
    ids, m = fuser.snapshot()[:2]
    assert counts['merged'] == 0 and len(ids) == 2
    nearest = np.linalg.norm(m[:, None] - truth[None], axis=-1).argmin(axis=1)
    assert sorted(nearest.tolist()) == [0, 1]


def test_counts_follow_merges_and_deletions_and_survive_a_restart(tmp_path):
    config = FuserConfig(map_file=str(tmp_path / 'map.json'), detection_probability=0.9,
                         **EAGER)
    fuser, a, b = _two_confirmed_tracks(config)
    tracker = fuser.tracker
    c = tracker.allocate(fuser.map)
    fuser.map.update([c, c], np.array([[5.0, 5.0]] * 2), 0.01 * np.eye(2)[None].repeat(2, 0),
                     np.zeros((2, 2, 2)), 'r', S)
    # An ID given to two rows of one message counts once; IDs not owned are ignored.
    tracker.note_sightings(np.array([a, a, c, 7], np.int64))
    _sightings(tracker, a, b, 20, 5, 1)
    tracker.note_sightings(np.array([b, c], np.int64))
    assert tracker.sightings == {a: 22, b: 7, c: 2}
    assert tracker.together == {a: {b: 1, c: 1}, b: {a: 1, c: 1}, c: {a: 1, b: 1}}
    assert tracker.merge(fuser.map, Counter()) == [(b, a)]
    # a and b seen in 22 + 7 - 1 messages; with c: 1 + 1 (an upper bound).
    assert tracker.sightings == {a: 28, c: 2}
    assert tracker.together == {a: {c: 2}, c: {a: 2}}
    assert fuser.save()
    document = json.loads((tmp_path / 'map.json').read_text())['tracks']
    assert document['sightings'] == [[a, 28], [c, 2]]
    assert document['together'] == [[a, c, 2]]
    restarted = Fuser(config, [SOURCE])
    restarted.load()
    assert restarted.tracker.sightings == tracker.sightings
    assert restarted.tracker.together == tracker.together
    assert restarted.tracker.apart == tracker.apart and tracker.apart[a][c] == 22
    # An older file: pairs without counts count once, no sightings.
    document = json.loads((tmp_path / 'map.json').read_text())
    document['tracks']['together'] = [[a, c]]
    del document['tracks']['sightings']
    (tmp_path / 'map.json').write_text(json.dumps(document))
    older = Fuser(config, [SOURCE])
    older.load()
    assert older.tracker.together == {a: {c: 1}, c: {a: 1}} and older.tracker.sightings == {}
    assert older.counters.counts['map_file_rejected'] == 0


def test_a_deleted_tentative_track_takes_its_counts_along():
    fuser = Fuser(FuserConfig(tentative_timeout_s=1.0), [SOURCE])
    R = np.broadcast_to(0.01 * np.eye(2), (2, 2, 2)).copy()
    for stamp in (S, 2 * S):
        fuser.add_landmarks(SOURCE, LandmarkMessage(
            stamp, [UNKNOWN_ID] * 2, np.array([[0.0, 0.0], [9.0, 0.0]]), R, 0 * R,
            scan=CERTAIN))
        fuser.fuse_queued()
    a, b = sorted(fuser.tracker.tentative)
    # They met in the second message (not in the first, which started them).
    assert fuser.tracker.sightings == {a: 2, b: 2} and fuser.tracker.together[a] == {b: 1}
    fuser.add_landmarks(SOURCE, LandmarkMessage(
        4 * S, [UNKNOWN_ID], np.array([[20.0, 0.0]]), R[:1], 0 * R[:1], scan=CERTAIN))
    fuser.fuse_queued()
    counts = fuser.sources[SOURCE].counts
    assert counts['deleted'] == 2 and a not in fuser.tracker.owned
    (c,) = fuser.tracker.tentative
    assert fuser.tracker.sightings == {c: 1} and fuser.tracker.together == {}


def test_p_D_must_make_distinct_landmarks_co_occur_more_than_duplicates():
    FuserConfig(detection_probability=0.05, merge_together_same=0.02)   # q = 0.026
    with pytest.raises(ValueError, match='merge_together_same'):
        FuserConfig(detection_probability=0.02, merge_together_same=0.02)   # q = 0.010


@pytest.mark.parametrize('met_again', [False, True])
def test_the_message_that_starts_a_track_is_no_meeting(met_again):
    # Package defaults (p_D unknown): B started by a row beside A's row in one message
    # (one landmark gives one row per scan: one of the two was not the landmark's),
    # then seen alone. Merged, unless the two meet again after B exists.
    fuser, a, b = _two_confirmed_tracks(FuserConfig())
    tracker = fuser.tracker
    tracker.note_sightings(np.array([a, b], np.int64), born=[b])
    assert tracker.sightings == {a: 1, b: 1} and tracker.together == {}
    _sightings(tracker, a, b, 5, 5, 0)
    if met_again:
        tracker.note_sightings(np.array([a, b], np.int64))
        assert tracker.together == {a: {b: 1}, b: {a: 1}}
        assert tracker.merge(fuser.map, Counter()) == []
    else:
        assert tracker.merge(fuser.map, Counter()) == [(b, a)]


@pytest.mark.parametrize('k, n, p_D, merged', [
    (0, 0, None, True), (0, 5, 0.9, True),          # never together
    (1, 40, None, False), (1, 40, 0.0, False),      # no p_D: kept apart
    (1, 40, 0.9, True),                             # rare meetings, p_D high
    (1, 40, 0.015, False),                          # q = 0.0076 <= same: no test
    (1, 5, 0.9, False),                             # too few messages for the threshold
    (12, 40, 0.99, False),                          # meets in 30 %: not "one landmark"
    (30, 300, 0.2, False),                          # q = 0.11: a pair would do that
    (3, 300, 0.9, True)])
def test_one_landmark_by_sightings_needs_a_fit_and_enough_evidence(k, n, p_D, merged):
    got = one_landmark_by_sightings(k, n, p_D, 0.01, 1e-3, 9.2)
    assert got is merged
    if k and p_D:
        q = p_D / (2 - p_D)
        plausible = stats.binom.sf(k - 1, n, 0.01) >= 1e-3
        ratio = stats.binom.logpmf(k, n, 0.01) - stats.binom.logpmf(k, n, q)
        assert got == (q > 0.01 and plausible and ratio >= 9.2)


def test_the_difference_distance_without_dependent_parts_is_the_plain_one(rng):
    n = 50
    d = rng.normal(0.0, 0.3, (n, 2))
    A = rng.normal(0.0, 0.2, (n, 2, 2))
    P_a = A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(2)
    P_b = 0.5 * P_a[::-1] + 0.02 * np.eye(2)
    zero = np.zeros((n, 2, 2))
    want = np.einsum('ni,ni->n', d, np.linalg.solve(P_a + P_b, d[..., None])[..., 0])
    for P_dep_a, P_dep_b in ((zero, zero), (0.5 * P_a, zero), (zero, 0.3 * P_b)):
        got = difference_mahalanobis_sq(d, P_a - P_dep_a, P_dep_a, P_b - P_dep_b, P_dep_b)
        np.testing.assert_allclose(got, want, rtol=1e-12)
    # With dependent parts on both sides the bound is below the plain distance.
    both = difference_mahalanobis_sq(d, 0.5 * P_a, 0.5 * P_a, 0.5 * P_b, 0.5 * P_b)
    assert np.all(both <= want * (1 + 1e-12)) and np.all(both < want)


@pytest.mark.parametrize('correlation', [1.0, 0.0, -1.0])
def test_the_difference_distance_of_one_landmark_passes_the_gate_at_its_rate(correlation):
    """
    Monte Carlo: two estimates of one landmark whose dependent errors correlate.

    Each estimate's error is an independent part plus a dependent one (covariances
    from a split-CI map); the dependent errors are equal, independent or opposite.
    The bound exceeds the 99 % gate in at most about 1 % of the draws whatever the
    correlation, and never exceeds the true distance; the plain distance on
    ``P_a + P_b`` exceeds it in a third of the draws with opposite errors.
    """
    rng = np.random.default_rng(5)
    n = 20000
    P_ind_a, P_dep_a = np.diag([0.002, 0.001]), np.array([[0.004, 0.001], [0.001, 0.003]])
    P_ind_b, P_dep_b = np.diag([0.001, 0.003]), np.array([[0.003, -0.001], [-0.001, 0.004]])
    e_ind = (rng.multivariate_normal([0, 0], P_ind_a, n)
             - rng.multivariate_normal([0, 0], P_ind_b, n))
    z = rng.standard_normal((n, 2))
    e_a = z @ np.linalg.cholesky(P_dep_a).T
    other = correlation * z + np.sqrt(1 - correlation ** 2) * rng.standard_normal((n, 2))
    e_b = other @ np.linalg.cholesky(P_dep_b).T
    d = e_ind + e_a - e_b
    L_a, L_b = np.linalg.cholesky(P_dep_a), np.linalg.cholesky(P_dep_b)
    cross = correlation * L_a @ L_b.T
    true_cov = P_ind_a + P_ind_b + P_dep_a + P_dep_b - cross - cross.T
    true_d2 = np.einsum('ni,ni->n', d, np.linalg.solve(true_cov, d.T).T)
    bound = difference_mahalanobis_sq(d, *(np.broadcast_to(P, (n, 2, 2)) for P in (
        P_ind_a, P_dep_a, P_ind_b, P_dep_b)))
    threshold = chi2_threshold(2, 0.99)
    assert np.all(bound <= true_d2 * (1 + 1e-9))
    assert np.mean(bound > threshold) <= 0.012
    plain = np.einsum('ni,ni->n', d, np.linalg.solve(P_ind_a + P_ind_b + P_dep_a + P_dep_b,
                                                     d.T).T)
    if correlation < 0:
        assert np.mean(plain > threshold) > 0.03
