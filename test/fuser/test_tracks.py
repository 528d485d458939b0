"""Tests of landmarks without IDs: fuser.tracks through Observer and Fuser, without ROS."""

from collections import Counter
import json

from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
import pytest

S = 1_000_000_000
SOURCES = ['/robot1/landmarks', '/robot2/landmarks']
FIRST = FuserConfig().first_new_id
EAGER = {'false_track_probability': 0.49}
"""A track score test that confirms a track on its second row, as ``min_observations``
2 did: for the tests of association and bookkeeping, not of the score."""

# The textbook exercise, case 5 (as in test/nodes/test_fuser_node.py).
POSE1, POSE1_COV, Z1 = np.array([1.0, 2.0, 0.5]), np.diag([0.08, 0.6, 0.02]), np.array([4.0, 0.7])
POSE2, POSE2_COV, Z2 = np.array([6.0, 4.0, 2.1]), np.diag([0.20, 0.09, 0.03]), np.array([4.0, 0.3])
M_CASE5 = np.array([2.58757252, 6.15534036])
P_CASE5 = np.array([[0.37966125, 0.07773125], [0.07773125, 0.36999739]])


def observe(observer, stamp_ns, pose, P_pose, z, ids=None, classes=None):
    """Return the one LandmarkBatch an observer places from a pose and an observation."""
    observer.add_pose(stamp_ns, pose, P_pose)
    z = np.atleast_2d(z)
    columns = {'range': z[:, 0], 'bearing': z[:, 1]}
    if ids is not None:
        columns['id'] = np.asarray(ids, np.int64)
    if classes is not None:
        columns['class'] = np.asarray(classes, np.int64)
    (batch,) = observer.add_observations([ObservationMessage(stamp_ns, columns)], stamp_ns)
    return batch


def feed(fuser, source, batch):
    """Queue an observer's batch in the fuser, as the nodes do."""
    return fuser.add_landmarks(source, LandmarkMessage(batch.stamp_ns, batch.ids, batch.m, batch.P,
                               batch.P_dep, classes=batch.classes, scan=batch.scan))


@pytest.mark.parametrize('ids', [None, [UNKNOWN_ID]])
def test_textbook_case5_without_ids_gives_the_labelled_landmark(ids):
    maps = []
    for labelled in (True, False):
        fuser = Fuser(FuserConfig(fusion='independent', **EAGER), SOURCES)
        config = ObserverConfig(range_stddev=0.5, bearing_stddev=0.2)
        for source, (pose, P_pose, z) in zip(SOURCES, [(POSE1, POSE1_COV, Z1),
                                                       (POSE2, POSE2_COV, Z2)]):
            batch = observe(Observer(config), 10 * S, pose, P_pose, z,
                            ids=[7] if labelled else ids)
            if not labelled:
                assert batch.ids.tolist() == [UNKNOWN_ID] and batch.scan is not None
                np.testing.assert_array_equal(batch.scan.robot_xy, pose[:2])
                np.testing.assert_array_equal(batch.scan.P_pose, P_pose)
            else:
                assert batch.scan is None and batch.classes is None
            feed(fuser, source, batch)
            fuser.fuse_queued()
        maps.append(fuser.snapshot())
    (ids7, m7, P7, _, n7), (ids_new, m, P, _, n) = maps
    assert ids7.tolist() == [7] and ids_new.tolist() == [FIRST]
    np.testing.assert_allclose(m[0], M_CASE5, rtol=0, atol=1e-8)
    np.testing.assert_allclose(P[0], P_CASE5, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(m, m7)
    np.testing.assert_array_equal(P, P7)
    counts = [fuser.sources[s].counts for s in SOURCES]
    assert counts[0]['new_tentative'] == 1 and counts[1]['associated'] == 1
    assert counts[0]['confirmed'] == 1


def scan_rows(truth, robot_xy, P_pose, R_noise, rng, offset=(0.0, 0.0)):
    """Return world rows of ``truth`` seen from ``robot_xy``, total covariances and Scan."""
    truth = np.asarray(truth, np.float64)
    e = truth - robot_xy
    J = np.zeros((len(truth), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = -e[:, 1], e[:, 0]
    P_pose_part = J @ P_pose @ J.transpose(0, 2, 1)
    noise = rng.multivariate_normal(np.zeros(2), R_noise, len(truth))
    m = truth + noise + np.asarray(offset)
    R = P_pose_part + R_noise
    return m, R, P_pose_part, Scan(np.asarray(robot_xy, np.float64), P_pose)


def test_two_landmarks_three_sigma_apart_stay_two(rng):
    sigma = 0.05
    truth = np.array([[0.0, 0.0], [3 * sigma, 0.0]])
    fuser = Fuser(FuserConfig(), SOURCES[:1])
    for k in range(40):
        m, R, R_dep, scan = scan_rows(truth, (0.0, -4.0), np.diag([1e-6, 1e-6, 1e-8]),
                                      sigma ** 2 * np.eye(2), rng)
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(
            (k + 1) * S, np.full(2, UNKNOWN_ID), m, R, R_dep, scan=scan))
        fuser.fuse_queued()
    ids, m, P, _, observations = fuser.snapshot()
    assert len(ids) == 2
    order = np.argsort(m[:, 0])
    np.testing.assert_allclose(m[order], truth, atol=3 * sigma)
    assert observations.sum() >= 40


def test_clutter_is_never_confirmed_and_its_tracks_expire(rng):
    fuser = Fuser(FuserConfig(tentative_timeout_s=5.0), SOURCES[:1])
    for k in range(100):
        m = rng.uniform(-200.0, 200.0, (1, 2))
        R = np.broadcast_to(0.01 * np.eye(2), (1, 2, 2)).copy()
        fuser.add_landmarks(SOURCES[0], LandmarkMessage((k + 1) * S, [UNKNOWN_ID], m, R, 0.5 * R,
                            scan=Scan(np.zeros(2), np.zeros((3, 3)))))
        fuser.fuse_queued()
    counts = fuser.sources[SOURCES[0]].counts
    assert len(fuser.map) == 0
    assert counts['new_tentative'] == 100 and counts['confirmed'] == 0
    assert counts['deleted'] >= 90
    assert len(fuser.tracker.tentative) <= 6


@pytest.mark.parametrize('association', ['jcbb', 'nearest_neighbour'])
def test_joint_compatibility_pairs_rows_shifted_by_a_shared_pose_error(association, rng):
    fuser = Fuser(FuserConfig(association=association), SOURCES)
    truth = np.array([[0.0, 0.0], [1.0, 0.0]])
    tight = np.broadcast_to(1e-4 * np.eye(2), (2, 2, 2)).copy()
    for k in range(2):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(
            (k + 1) * S, [1, 2], truth, tight, 0 * tight))
    fuser.fuse_queued()
    assert fuser.snapshot().ids.tolist() == [1, 2]
    # Robot 2's x error of 0.6 m shifts both rows; its pose covariance says so.
    P_pose = np.diag([0.25, 1e-4, 0.0])
    m, R, R_dep, scan = scan_rows(truth, (0.5, -3.0), P_pose, 4e-4 * np.eye(2),
                                  np.random.default_rng(3), offset=(0.6, 0.0))
    fuser.add_landmarks(SOURCES[1], LandmarkMessage(
        3 * S, np.full(2, UNKNOWN_ID), m, R, R_dep, scan=scan))
    fuser.fuse_queued()
    observations = dict(zip(*[a.tolist() for a in fuser.snapshot()[::4]]))
    if association == 'jcbb':
        assert observations == {1: 3, 2: 3}
    else:  # nearest neighbour takes the closer landmark 2 for both rows
        assert observations == {1: 2, 2: 4}
    assert fuser.sources[SOURCES[1]].counts['associated'] == 2


def test_ambiguous_rows_are_skipped_on_request(rng):
    fuser = Fuser(FuserConfig(association='nearest_neighbour', ambiguous_rows='skip'), SOURCES)
    tight = np.broadcast_to(1e-2 * np.eye(2), (2, 2, 2)).copy()
    for k in range(2):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage((k + 1) * S, [1, 2],
                            np.array([[0.0, 0.0], [0.2, 0.0]]), tight, 0 * tight))
    fuser.add_landmarks(SOURCES[1], LandmarkMessage(
        3 * S, [UNKNOWN_ID], np.array([[0.1, 0.0]]), tight[:1], 0 * tight[:1]))
    fuser.fuse_queued()
    counts = fuser.sources[SOURCES[1]].counts
    assert counts['ambiguous'] == 1 and counts['associated'] == 0
    assert counts['new_tentative'] == 0
    assert fuser.snapshot().observations.tolist() == [2, 2]


def test_classes_keep_landmarks_apart_and_are_published(rng):
    fuser = Fuser(FuserConfig(**EAGER), SOURCES[:1])
    C = np.broadcast_to(1e-2 * np.eye(2), (2, 2, 2)).copy()
    for k in range(3):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage((k + 1) * S, np.full(2, UNKNOWN_ID),
                            np.array([[0.0, 0.0], [0.01, 0.0]]), C, 0 * C, classes=[3, 5],
                            scan=Scan(np.zeros(2), np.zeros((3, 3)))))
        fuser.fuse_queued()
    ids = fuser.snapshot().ids
    assert ids.tolist() == [FIRST, FIRST + 1]
    assert fuser.classes_of(ids).tolist() == [3, 5]


def test_allocated_ids_persist_across_a_restart_and_never_collide(tmp_path, rng):
    path = str(tmp_path / 'map.json')
    config = FuserConfig(map_file=path, first_new_id=100, **EAGER)
    fuser = Fuser(config, SOURCES[:1])
    C = np.broadcast_to(1e-2 * np.eye(2), (1, 2, 2)).copy()
    # A labelled row may not take 100: IDs from first_new_id up are the allocator's.
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, [100], np.array([[50.0, 50.0]]), C, 0 * C))
    for k in range(2):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(
            (k + 2) * S, [UNKNOWN_ID], np.array([[0.0, 0.0]]), C, 0 * C, classes=[4]))
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(
        5 * S, [UNKNOWN_ID], np.array([[9.0, 9.0]]), C, 0 * C))
    fuser.fuse_queued()
    assert fuser.counters['id_reserved'] == 1
    assert fuser.snapshot().ids.tolist() == [100]
    assert fuser.save()
    document = json.load(open(path))
    assert document['next_id'] == 102 and document['version'] == 1
    assert [r['class'] for r in document['landmarks']] == [4]

    restarted = Fuser(config, SOURCES[:1])
    restarted.load()
    assert restarted.tracker.next_id == 102
    assert restarted.classes_of(np.array([100])).tolist() == [4]
    for k in range(2):
        restarted.add_landmarks(SOURCES[0], LandmarkMessage((k + 10) * S, [UNKNOWN_ID],
                                np.array([[-7.0, 3.0]]), C, 0 * C))
    # Of class 4, like landmark 100: associated with it.
    restarted.add_landmarks(SOURCES[0], LandmarkMessage(
        12 * S, [UNKNOWN_ID], np.array([[0.01, 0.0]]), C, 0 * C, classes=[4]))
    restarted.fuse_queued()
    ids, _, _, _, observations = restarted.snapshot()
    assert ids.tolist() == [100, 102] and observations.tolist() == [3, 2]


def test_labelled_rows_with_classes_fuse_exactly_as_before(rng):
    plain, classed = (Fuser(FuserConfig(), SOURCES) for _ in range(2))
    for k in range(8):
        ids = np.arange(5)
        m = np.column_stack([ids, 2.0 * ids]) + rng.normal(0, 0.05, (5, 2))
        P = np.broadcast_to(np.diag([0.04, 0.09]), (5, 2, 2)).copy()
        plain.add_landmarks(SOURCES[k % 2], LandmarkMessage((k + 1) * S, ids, m, P, 0.25 * P))
        classed.add_landmarks(SOURCES[k % 2], LandmarkMessage((k + 1) * S, ids, m, P, 0.25 * P,
                              classes=ids % 2))
    plain.fuse_queued()
    classed.fuse_queued()
    for a, b in zip(plain.snapshot(), classed.snapshot(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert classed.classes_of(np.arange(5)).tolist() == [0, 1, 0, 1, 0]
    assert not plain.tracker.tentative


@pytest.mark.parametrize('met', [False, True])
def test_compatible_tracks_that_never_met_are_merged(met):
    fuser = Fuser(FuserConfig(), SOURCES[:1])
    tracker, C = fuser.tracker, np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)).copy()
    a, b = tracker.allocate(fuser.map), tracker.allocate(fuser.map)
    fuser.map.update([a, a, a], np.array([[0.0, 0.0]] * 3), C, 0 * C, 'r', S)
    fuser.map.update([b, b], np.array([[0.05, 0.0]] * 2), C[:2], 0 * C[:2], 'r', S)
    if met:
        tracker.note_sightings(np.array([a, b]))
    counts = fuser.sources[SOURCES[0]].counts
    merged = tracker.merge(fuser.map, counts)
    if met:
        assert merged == [] and fuser.snapshot().ids.tolist() == [a, b]
    else:
        assert merged == [(b, a)] and counts['merged'] == 1
        assert fuser.snapshot().ids.tolist() == [a] and tracker.resolve(b) == a


def test_partial_rows_without_an_id_are_rejected_by_the_observer():
    observer = Observer(ObserverConfig())
    observer.add_pose(S, np.zeros(3), np.zeros((3, 3)))
    columns = {'range': np.array([2.0, 3.0])}
    (batch,) = observer.add_observations([ObservationMessage(S, columns)], S)
    assert len(batch.ids) == 0 and len(batch.partial_observations) == 0
    assert observer.counters.counts['partial_without_id'] == 2


def _batch_independent_run(chunks):
    """Fuse a fixed sequence of unlabelled messages, calling fuse_queued after ``chunks``."""
    fuser = Fuser(FuserConfig(tentative_timeout_s=5.0), SOURCES)
    R = np.broadcast_to(0.01 * np.eye(2), (1, 2, 2)).copy()
    scan = Scan(np.zeros(2), np.zeros((3, 3)))
    # A: a track at (0, 0); B, far away, moves the clock past A's timeout; C comes
    # back to (0, 0) with an older stamp from the other robot (A must be gone, however
    # the messages were batched); then D..G confirm a track from both sources.
    sequence = [(SOURCES[0], 1.0, (0.0, 0.0)), (SOURCES[1], 6.5, (50.0, 0.0)),
                (SOURCES[0], 6.2, (0.01, 0.0)), (SOURCES[0], 7.0, (20.0, 0.0)),
                (SOURCES[0], 7.1, (20.0, 0.0)), (SOURCES[1], 7.2, (20.05, 0.0)),
                (SOURCES[1], 7.3, (20.05, 0.0)), (SOURCES[0], 7.4, (30.0, 0.0))]
    for k, (source, t, point) in enumerate(sequence):
        fuser.add_landmarks(source, LandmarkMessage(
            int(t * S), [UNKNOWN_ID], np.array([point]), R, 0.5 * R, scan=scan))
        if k in chunks:
            fuser.fuse_queued()
    fuser.fuse_queued()
    counts = sum((state.counts for state in fuser.sources.values()), Counter())
    return fuser, counts


def test_expiry_and_merging_do_not_depend_on_where_fuse_batches_end():
    runs = [_batch_independent_run(chunks) for chunks in (
        set(range(8)), set(), {1}, {2, 5}, {0, 3, 4, 6})]
    first, counts = runs[0]
    # The clock reached 6.5 s before C: A's track (started at 1 s) was deleted, C
    # started its own.
    assert counts['deleted'] >= 1 and counts['confirmed'] == 1
    assert first.snapshot().ids.tolist() == [FIRST + 3]
    for fuser, other in runs[1:]:
        for a, b in zip(first.snapshot(), fuser.snapshot(), strict=True):
            np.testing.assert_array_equal(a, b)
        assert fuser.tracker.next_id == first.tracker.next_id
        assert sorted(fuser.tracker.tentative) == sorted(first.tracker.tentative)
        assert fuser.tracker.merged_into == first.tracker.merged_into
        assert {k: other[k] for k in ('deleted', 'merged', 'confirmed', 'new_tentative')} == {
            k: counts[k] for k in ('deleted', 'merged', 'confirmed', 'new_tentative')}


@pytest.mark.parametrize('fusion', ['independent', 'split_covariance_intersection'])
def test_a_merge_fuses_the_retired_track_into_the_kept_one(fusion, rng):
    fuser = Fuser(FuserConfig(fusion=fusion), SOURCES[:1])
    tracker = fuser.tracker
    a, b = tracker.allocate(fuser.map), tracker.allocate(fuser.map)
    z = np.array([[0.0, 0.0], [0.02, -0.01], [-0.01, 0.02], [0.05, 0.0], [0.04, 0.01]])
    R = np.array([np.diag(d) for d in rng.uniform(0.005, 0.02, (5, 2))])
    R_dep = 0.3 * R
    sources = np.array(['r1', 'r2', 'r1', 'r2', 'r2'])
    fuser.map.update([a, a, a], z[:3], R[:3], R_dep[:3], sources[:3], S)
    fuser.map.update([b, b], z[3:], R[3:], R_dep[3:], sources[3:], S)
    merged = tracker.merge(fuser.map, Counter())
    assert merged == [(b, a)]
    # The same rows all under one ID, in one map: what the kept landmark must hold.
    from landmark_ros.fusion.landmark_map import LandmarkMap
    reference = LandmarkMap(fusion, 0.999, 2, 5)
    reference.update([a, a, a], z[:3], R[:3], R_dep[:3], sources[:3], S)
    reference.update([a, a], z[3:], R[3:], R_dep[3:], sources[3:], S)
    got, want = fuser.map.snapshot(), reference.snapshot()
    assert got.ids.tolist() == [a] and got.observations.tolist() == [5]
    np.testing.assert_allclose(got.m, want.m, atol=1e-12)
    np.testing.assert_allclose(got.P, want.P, atol=1e-12)
    np.testing.assert_allclose(got.P_dep, want.P_dep, atol=1e-12)
    assert fuser.map.known(np.array([b]))[0] and tracker.resolve(b) == a


def test_merges_are_announced_once_with_the_kept_landmark_updated():
    fuser = Fuser(FuserConfig(), SOURCES[:1])
    tracker, C = fuser.tracker, np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)).copy()
    a, b = tracker.allocate(fuser.map), tracker.allocate(fuser.map)
    fuser.map.update([a, a, a], np.array([[0.0, 0.0]] * 3), C, 0 * C, 'r', S)
    fuser.map.update([b, b], np.array([[0.05, 0.0]] * 2), C[:2], 0 * C[:2], 'r', S)
    fuser.take_updates()
    # A message without an ID that changes b runs the merge check.
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(
        2 * S, [UNKNOWN_ID], np.array([[0.05, 0.0]]), C[:1], 0 * C[:1],
        scan=Scan(np.zeros(2), np.zeros((3, 3)))))
    fuser.fuse_queued()
    assert fuser.take_removed() == [(b, a)] and fuser.take_removed() == []
    assert a in fuser.take_updates().ids.tolist()
    assert fuser.snapshot().ids.tolist() == [a]


def _unlabelled_messages(rng, count=40):
    """Messages without IDs: 6 landmarks, rows from two sources, noise 0.05 m."""
    truth = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0], [3.0, 3.0], [6.0, 0.0], [6.0, 3.0]])
    R = np.broadcast_to(0.0025 * np.eye(2), (2, 2, 2)).copy()
    for k in range(count):
        seen = rng.choice(len(truth), 2, replace=False)
        m = truth[seen] + rng.normal(0.0, 0.05, (2, 2))
        yield SOURCES[k % 2], (k + 1) * S, m, R


def _feed_unlabelled(fuser, messages):
    for source, stamp, m, R in messages:
        fuser.add_landmarks(source, LandmarkMessage(stamp, [UNKNOWN_ID] * len(m), m, R, 0.2 * R,
                            scan=Scan(np.zeros(2), np.zeros((3, 3)))))
        fuser.fuse_queued()


def test_a_restart_resumes_tentative_tracks_and_merge_bookkeeping(tmp_path, rng):
    path = str(tmp_path / 'map.json')
    config = FuserConfig(min_observations=4, map_file=path)
    messages = list(_unlabelled_messages(rng))
    running = Fuser(config, SOURCES)
    _feed_unlabelled(running, messages[:13])
    assert running.tracker.tentative and running.tracker.together
    running.tracker.merged_into[FIRST + 999] = FIRST    # bookkeeping of an earlier merge
    assert running.save()
    document = json.loads((tmp_path / 'map.json').read_text())
    assert {t['id'] for t in document['tracks']['tentative']} == set(running.tracker.tentative)
    restarted = Fuser(config, SOURCES)
    restarted.load()
    for name in ('owned', 'sightings', 'together', 'merged_into', 'now_ns', 'next_id'):
        assert getattr(restarted.tracker, name) == getattr(running.tracker, name), name
    assert sorted(restarted.tracker.tentative) == sorted(running.tracker.tentative)
    # Both go on with the same messages: the restarted one is the running one.
    _feed_unlabelled(running, messages[13:])
    _feed_unlabelled(restarted, messages[13:])
    for a, b in zip(running.snapshot(), restarted.snapshot(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert sorted(restarted.tracker.tentative) == sorted(running.tracker.tentative)
    assert restarted.tracker.next_id == running.tracker.next_id


def test_a_file_without_tracks_loads_and_a_bad_tracks_section_is_quarantined(tmp_path, rng):
    path = tmp_path / 'map.json'
    config = FuserConfig(min_observations=4, map_file=str(path))
    fuser = Fuser(config, SOURCES)
    _feed_unlabelled(fuser, list(_unlabelled_messages(rng))[:13])
    assert fuser.save()
    document = json.loads(path.read_text())
    landmarks = len(document['landmarks'])
    del document['tracks']
    path.write_text(json.dumps(document))
    old = Fuser(config, SOURCES)
    old.load()
    assert len(old.map) == landmarks and not old.tracker.tentative
    document['tracks'] = {'tentative': [{'id': -3, 'class': 0, 'first_stamp_ns': 1,
                                         'source': 'x', 'rows': []}]}
    path.write_text(json.dumps(document))
    bad = Fuser(config, SOURCES)
    bad.load()
    assert len(bad.map) == landmarks and not bad.tracker.tentative
    assert bad.counters.counts['map_records_rejected'] == 1 and path.exists()
    assert len(list(tmp_path.glob('map.json.quarantine-*'))) == 1


def test_a_tentative_track_with_a_bad_row_is_dropped_alone(tmp_path, rng):
    path = tmp_path / 'map.json'
    config = FuserConfig(min_observations=4, map_file=str(path))
    fuser = Fuser(config, SOURCES)
    _feed_unlabelled(fuser, list(_unlabelled_messages(rng))[:13])
    assert fuser.save()
    document = json.loads(path.read_text())
    tentative = document['tracks']['tentative']
    good = dict(json.loads(json.dumps(tentative[0])), id=tentative[0]['id'] + 100)  # valid
    tentative.append(good)
    tentative[0]['rows'][0]['mean'] = [1e17, 0.0]
    path.write_text(json.dumps(document))
    again = Fuser(config, SOURCES)
    again.load()
    assert sorted(again.tracker.tentative) == sorted(t['id'] for t in tentative[1:])
    assert again.tracker.rejected_tracks == [(tentative[0]['id'], ['landmark_out_of_range'])]
    assert again.counters['map_records_rejected'] == 1


def test_shard_of_position_numbers_the_cells():
    from landmark_ros.fuser.sources import shard_of_position
    m = np.array([[5.0, 5.0], [25.0, 5.0], [-5.0, 5.0], [5.0, 25.0], [np.nan, 1.0]])
    # Cells (0, 0), (1, 0), (-1, 0), (0, 1); side 20 m; 3 shards.
    assert shard_of_position(m, 20.0, 3).tolist() == [0, 1, 2, 31 % 3, 0]


def test_shards_split_rows_without_ids_by_cell_and_own_their_ids(rng):
    centres = np.array([[5.0, 5.0], [25.0, 5.0], [45.0, 5.0], [5.0, 25.0], [25.0, 25.0]])
    one = Fuser(FuserConfig(), SOURCES)
    shards = [Fuser(FuserConfig(shard_count=2, shard_index=k), SOURCES) for k in range(2)]
    R = np.broadcast_to(0.0025 * np.eye(2), (5, 2, 2)).copy()
    for k in range(6):
        m = centres + rng.normal(0.0, 0.05, (5, 2))
        for fuser in [one] + shards:
            fuser.add_landmarks(SOURCES[k % 2], LandmarkMessage(
                (k + 1) * S, [UNKNOWN_ID] * 5, m, R, 0.2 * R,
                scan=Scan(np.zeros(2), np.zeros((3, 3)))))
            fuser.fuse_queued()
    whole = one.snapshot()
    parts = [shard.snapshot() for shard in shards]
    assert len(whole.ids) == 5 == sum(len(p.ids) for p in parts)
    for k, part in enumerate(parts):
        assert all(i % 2 == k for i in part.ids.tolist())     # each shard's own IDs
    # The same landmarks, estimated from the same rows.
    order = np.lexsort(whole.m.T)
    joined = np.concatenate([p.m for p in parts])
    np.testing.assert_allclose(joined[np.lexsort(joined.T)], whole.m[order], atol=1e-12)
    in_shard = [int((shard_of(centres) == k).sum()) for k in range(2)]
    for k, shard in enumerate(shards):
        counts = sum((state.counts for state in shard.sources.values()), Counter())
        assert counts['other_shard'] == 6 * (5 - in_shard[k])


def shard_of(m):
    """Return the shard (of 2, 20 m cells) of positions."""
    from landmark_ros.fuser.sources import shard_of_position
    return shard_of_position(m, 20.0, 2)
