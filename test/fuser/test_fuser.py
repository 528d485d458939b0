"""Tests of fuser.Fuser, without ROS: queues, checks, fusion, status, map file."""

import json
import logging

from landmark_ros.fuser import map_file
from landmark_ros.fuser.fuser import Fuser, LandmarkMessage
from landmark_ros.fuser.map_file import check_records
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import UNKNOWN_ID
import numpy as np
import pytest

S = 1_000_000_000
C = np.diag([0.04, 0.09])
SOURCES = ['/robot1/landmarks', '/robot2/landmarks']


def rows(n, rng, spread=0.05, ids=None):
    """Return n landmark rows around (i, 2 i) for ids i."""
    ids = np.arange(n) if ids is None else np.asarray(ids)
    m = np.column_stack([ids * 1.0, ids * 2.0]) + rng.normal(0.0, spread, (len(ids), 2))
    P = np.broadcast_to(C, (len(ids), 2, 2)).copy()
    return ids, m, P, 0.25 * P


def problems(fuser):
    """Return the non-zero problem counters of the fuser."""
    return {k: v for k, v in fuser.counters.counts.items()
            if v and k not in ('landmarks_confirmed', 'saves')}


@pytest.mark.parametrize('fusion', ['independent', 'covariance_intersection',
                                    'split_covariance_intersection'])
def test_queued_messages_fuse_as_the_map_would(fusion, rng):
    fuser = Fuser(FuserConfig(fusion=fusion), SOURCES)
    reference = LandmarkMap(fusion)
    for k in range(6):
        source = SOURCES[k % 2]
        ids, m, P, P_dep = rows(5, rng)
        assert fuser.add_landmarks(source, LandmarkMessage((k + 1) * S, ids, m, P, P_dep)) == 5
        reference.update(ids, m, P, P_dep, source, (k + 1) * S)
    result = fuser.fuse_queued()
    assert result.changed and fuser.map_changed and fuser.unsaved
    for a, b in zip(fuser.snapshot(), reference.snapshot(), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert not fuser.map_changed
    assert fuser.sources[SOURCES[0]].counts['fused'] == 15
    assert fuser.fuse_queued() is None


def test_bad_rows_are_counted_per_source_and_good_rows_kept(rng):
    fuser = Fuser(FuserConfig(), SOURCES)
    ids, m, P, P_dep = rows(4, rng)
    m[1, 0] = np.nan
    P[2] = -P[2]
    ids[3] = -1
    assert fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, ids, m, P, P_dep)) == 1
    assert fuser.sources[SOURCES[0]].counts['landmark_nonfinite'] == 1
    assert problems(fuser) == {'landmark_nonfinite': 1, 'covariance_not_psd': 1,
                               'invalid_id': 1}


def test_wrong_frame_and_queue_overflow(rng):
    fuser = Fuser(FuserConfig(max_queue_messages=2), SOURCES)
    assert fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng), frame_id='odom')) == 0
    for k in range(3):
        fuser.add_landmarks(SOURCES[1], LandmarkMessage(S + k, *rows(3, rng), frame_id='map'))
    assert fuser.queued_messages() == 2
    assert problems(fuser) == {'wrong_frame': 1, 'queue_overflow': 3}


def burst(rng):
    """Return six messages: bad rows, a wrong frame, an all-bad one, one without an ID."""
    messages = []
    for k in range(6):
        ids, m, P, P_dep = rows(4, rng)
        if k == 1:
            m[1, 0], P[2] = np.nan, -P[2]
        if k == 3:
            ids[:] = -5
        if k == 5:
            ids[0] = UNKNOWN_ID
        messages.append(LandmarkMessage((k + 1) * S, ids, m, P, P_dep,
                                        'odom' if k == 2 else 'map', np.full(4, k)))
    return messages


@pytest.mark.parametrize('depth', [2, 100])
def test_a_burst_is_queued_as_its_messages_one_by_one(depth, rng):
    # add_landmark_messages checks the rows of a burst together; the queues, counters
    # and the fused map must be those of add_landmarks called message by message.
    messages = burst(rng)
    one, many = (Fuser(FuserConfig(max_queue_messages=depth), SOURCES) for _ in range(2))
    queued = sum(one.add_landmarks(SOURCES[0], message, 7) for message in messages)
    assert many.add_landmark_messages(SOURCES[0], messages, 7) == queued
    assert queued == 4 + 2 + 4 + 4
    assert many.queued_messages() == min(depth, 4)
    assert one.sources[SOURCES[0]].counts == many.sources[SOURCES[0]].counts
    assert one.sources[SOURCES[0]].last_message_ns == many.sources[SOURCES[0]].last_message_ns
    assert problems(one) == problems(many) != {}
    # What is queued, against the messages themselves: message 1 without its bad rows
    # 1 and 2, message 2 (wrong frame) and 3 (no valid row) not at all.
    expected = [(k, rows) for k, rows in ((0, [0, 1, 2, 3]), (1, [0, 3]), (4, [0, 1, 2, 3]),
                                          (5, [0, 1, 2, 3]))][-depth:]
    for item, (k, kept) in zip(many.sources[SOURCES[0]].queue, expected, strict=True):
        assert (item.stamp_ns, item.unlabelled) == (messages[k].stamp_ns, k == 5)
        for got, given in zip((item.ids, item.m, item.P, item.P_dep, item.classes),
                              messages[k][1:5] + (messages[k].classes,)):
            np.testing.assert_array_equal(got, np.asarray(given)[kept])
        assert item.ids.dtype == np.int64 and item.m.dtype == np.float64
    for a, b in zip(one.sources[SOURCES[0]].queue, many.sources[SOURCES[0]].queue,
                    strict=True):
        assert (a.stamp_ns, a.unlabelled) == (b.stamp_ns, b.unlabelled)
        for x, y in zip((a.ids, a.m, a.P, a.P_dep, a.classes),
                        (b.ids, b.m, b.P, b.P_dep, b.classes), strict=True):
            np.testing.assert_array_equal(x, y)
    one.fuse_queued(), many.fuse_queued()
    for a, b in zip(one.snapshot(), many.snapshot(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(one.map) > 0
    assert many.add_landmark_messages(SOURCES[0], []) == 0


@pytest.mark.parametrize('shards', [1, 2])
def test_bursts_of_several_sources_are_queued_as_each_source_alone(shards, rng):
    # add_landmark_bursts checks the rows of all sources together; queues, counters
    # (per source) and the fused map must be those of add_landmark_messages per source.
    clean = [LandmarkMessage((k + 1) * S, *rows(4, rng), 'map') for k in range(3)]
    bursts = [(SOURCES[0], burst(rng)), (SOURCES[1], clean), (SOURCES[0], clean[:1])]
    config = FuserConfig(shard_count=shards)
    alone, together = (Fuser(config, SOURCES) for _ in range(2))
    queued = sum(alone.add_landmark_messages(source, messages, 7)
                 for source, messages in bursts)
    assert together.add_landmark_bursts(bursts, 7) == queued > 0
    for source in SOURCES:
        assert alone.sources[source].counts == together.sources[source].counts
        for a, b in zip(alone.sources[source].queue, together.sources[source].queue,
                        strict=True):
            assert (a.sequence, a.stamp_ns) == (b.sequence, b.stamp_ns)
            np.testing.assert_array_equal(a.ids, b.ids)
            np.testing.assert_array_equal(a.P, b.P)
    assert problems(alone) == problems(together) != {}
    alone.fuse_queued(), together.fuse_queued()
    for a, b in zip(alone.snapshot(), together.snapshot(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert together.add_landmark_bursts([]) == 0


def test_statuses_name_stale_sources_and_new_problems(rng):
    fuser = Fuser(FuserConfig(source_timeout_s=1.0), SOURCES)
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(2, rng)), now_ns=10 * S)
    first, one, two = fuser.statuses(10 * S + S // 2)
    assert (one.name, one.level, two.name, two.level) == (SOURCES[0], 'ok', SOURCES[1], 'warn')
    assert first.level == 'warn' and f'stale: {SOURCES[1]}' in first.message
    fuser.add_landmarks(SOURCES[1], LandmarkMessage(S, *rows(2, rng)), now_ns=10 * S)
    first, _, _ = fuser.statuses(10 * S + S // 2)
    assert first.level == 'ok' and first.extra['fusion'] == 'split_covariance_intersection'


def test_reset_clears_map_and_queues(rng):
    fuser = Fuser(FuserConfig(), SOURCES)
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng)))
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng)))
    fuser.fuse_queued()
    fuser.add_landmarks(SOURCES[1], LandmarkMessage(S, *rows(3, rng)))
    assert fuser.reset() == 3 and len(fuser.map) == 0 and fuser.queued_messages() == 0


def test_save_and_load_round_trip(tmp_path, rng):
    path = str(tmp_path / 'map.json')
    fuser = Fuser(FuserConfig(map_file=path), SOURCES)
    for _ in range(3):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(4, rng)))
    fuser.fuse_queued()
    assert fuser.save() and not fuser.unsaved
    again = Fuser(FuserConfig(map_file=path), SOURCES)
    again.load()
    for a, b in zip(again.snapshot(), fuser.snapshot(), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def saved_map(tmp_path, rng):
    """Return the path and JSON document of a saved map with three landmarks."""
    path = str(tmp_path / 'map.json')
    fuser = Fuser(FuserConfig(map_file=path), SOURCES)
    for _ in range(2):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng)))
    fuser.fuse_queued()
    assert fuser.save()
    with open(path) as stream:
        return path, json.load(stream)


@pytest.mark.parametrize('field, value, reason', [
    ('id', 2 ** 32 + 7, 'is not an integer in'),
    ('id', -1, 'is not an integer in'),
    ('id', 1.5, 'is not an integer in'),
    ('id', True, 'is not an integer in'),
    ('covariance', [[-1.0, 0.0], [0.0, -1.0]], 'covariance_not_psd'),
    ('covariance', [[4.4e-201, 0.0], [0.0, 4.4e-201]], 'covariance_too_small'),
    ('mean', [0.0, 'x'], 'could not convert'),
    ('mean', [1e17, 0.0], 'landmark_out_of_range'),
    ('covariance_dependent', [[1.0, 0.0], [0.0, 1.0]], 'dependent_part_invalid'),
    ('mean', [1.0], 'cannot reshape'),
])
def test_a_bad_record_is_quarantined_and_the_others_kept(
        tmp_path, rng, caplog, field, value, reason):
    path, document = saved_map(tmp_path, rng)
    document['landmarks'][1][field] = value
    with open(path, 'w') as stream:
        json.dump(document, stream)
    logger = logging.getLogger('fuser-test')
    fuser = Fuser(FuserConfig(map_file=path), SOURCES, logger)
    with caplog.at_level(logging.ERROR, 'fuser-test'):
        fuser.load()
    assert sorted(fuser.snapshot()[0].tolist()) == [0, 2]
    assert fuser.counters['map_records_rejected'] == 1
    assert fuser.counters['map_file_rejected'] == 0
    assert 'landmarks record 1' in caplog.text and reason in caplog.text
    quarantined, = tmp_path.glob('map.json.quarantine-*.json')
    rejected = json.loads(quarantined.read_text())['rejected']
    assert [(r['section'], r['index']) for r in rejected] == [('landmarks', 1)]
    assert (tmp_path / 'map.json').exists() and not list(tmp_path.glob('map.json.bad-*'))


@pytest.mark.parametrize('section, value', [
    ('next_id', 'many'), ('tracks', {'tentative': 'x'}), ('waiting_views', [{'id': 'x'}])])
def test_a_bad_section_is_quarantined_and_the_landmarks_kept(tmp_path, rng, section, value):
    path, document = saved_map(tmp_path, rng)
    document[section] = value
    with open(path, 'w') as stream:
        json.dump(document, stream)
    fuser = Fuser(FuserConfig(map_file=path), SOURCES)
    fuser.load()
    assert sorted(fuser.snapshot()[0].tolist()) == [0, 1, 2]
    assert fuser.counters['map_records_rejected'] == 1
    assert fuser.tracker.next_id >= FuserConfig().first_new_id


def test_a_labelled_row_in_the_reserved_range_never_takes_an_allocated_id(tmp_path, rng):
    path = str(tmp_path / 'map.json')
    fuser = Fuser(FuserConfig(map_file=path), SOURCES)
    first = FuserConfig().first_new_id
    _, m, P, P_dep = rows(3, rng)
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(
        S, np.array([1, first, first + 1]), m, P, P_dep))
    fuser.fuse_queued()
    assert fuser.counters['id_reserved'] == 2
    assert fuser.sources[SOURCES[0]].counts['id_reserved'] == 2
    assert fuser.snapshot()[0].tolist() in ([], [1])
    assert fuser.save()
    # A restart with a higher first_new_id keeps the range the file was made with.
    again = Fuser(FuserConfig(map_file=path, first_new_id=first + 10 ** 6), SOURCES)
    again.load()
    assert again.reserved_from == first
    _, m, P, P_dep = rows(1, rng)
    again.add_landmarks(SOURCES[1], LandmarkMessage(S, np.array([first + 1]), m, P, P_dep))
    assert again.counters['id_reserved'] == 1


def test_check_records_takes_exactly_the_live_row_checks(tmp_path, rng):
    _, document = saved_map(tmp_path, rng)
    check_records(document['landmarks'])                  # a file the fuser wrote passes
    document['landmarks'][2]['mean'] = [0.0, float('nan')]
    with pytest.raises(ValueError, match='record 2: .*landmark_nonfinite'):
        check_records(document['landmarks'])


def test_save_never_writes_a_non_finite_number(tmp_path, rng):
    path = tmp_path / 'map.json'
    fuser = Fuser(FuserConfig(map_file=str(path)), SOURCES)
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng)))
    fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(3, rng)))
    fuser.fuse_queued()
    assert fuser.save()
    before = path.read_text()
    fuser.map.mean[0, 0] = np.nan                         # whatever poisoned it
    assert not fuser.save()
    assert fuser.counters['save_failed'] == 1 and path.read_text() == before
    assert not list(tmp_path.glob('.map.json.*.tmp'))


def test_a_corrupt_file_is_moved_aside(tmp_path):
    path = tmp_path / 'map.json'
    path.write_text('{"format": "landmark_ros/map", ')
    fuser = Fuser(FuserConfig(map_file=str(path)), SOURCES)
    fuser.load()
    assert fuser.counters['map_file_rejected'] == 1 and not path.exists()
    assert map_file.VERSION == 1


def test_duplicate_sources_are_refused():
    with pytest.raises(ValueError, match='twice'):
        Fuser(FuserConfig(), ['/a', '/a'])


def test_take_updates_returns_only_the_landmarks_changed_since_last_time(rng):
    fuser = Fuser(FuserConfig(fusion='independent'), SOURCES)
    for _ in range(2):
        fuser.add_landmarks(SOURCES[0], LandmarkMessage(S, *rows(6, rng)))
    fuser.fuse_queued()
    assert fuser.take_updates().ids.tolist() == list(range(6))
    assert fuser.take_updates().ids.tolist() == []
    fuser.add_landmarks(SOURCES[1], LandmarkMessage(2 * S, *rows(2, rng, ids=[4, 1])))
    fuser.fuse_queued()
    updates = fuser.take_updates()
    full = fuser.snapshot()
    assert updates.ids.tolist() == [1, 4]
    for a, b in zip(updates, full, strict=True):
        np.testing.assert_array_equal(a, b[[1, 4]])


@pytest.mark.parametrize('fusion', ['independent', 'split_covariance_intersection'])
def test_two_shards_together_give_the_map_of_one_fuser(fusion, rng):
    one = Fuser(FuserConfig(fusion=fusion), SOURCES)
    shards = [Fuser(FuserConfig(fusion=fusion, shard_count=2, shard_index=k), SOURCES)
              for k in range(2)]
    for k in range(8):
        batch = rows(9, rng, spread=0.1)
        for fuser in [one] + shards:
            fuser.add_landmarks(SOURCES[k % 2], LandmarkMessage((k + 1) * S, *batch))
        if k % 3 == 2:
            for fuser in [one] + shards:
                fuser.fuse_queued()
    for fuser in [one] + shards:
        fuser.fuse_queued()
    whole = one.snapshot()
    parts = [shard.snapshot() for shard in shards]
    assert parts[0].ids.tolist() == [0, 2, 4, 6, 8] and parts[1].ids.tolist() == [1, 3, 5, 7]
    order = np.argsort(np.concatenate([p.ids for p in parts]))
    for j, column in enumerate(whole):
        joined = np.concatenate([p[j] for p in parts])[order]
        np.testing.assert_array_equal(joined, column)
    assert shards[0].sources[SOURCES[0]].counts['other_shard'] == 4 * 4
    assert 'other_shard' not in problems(shards[0])


def test_shard_index_must_be_below_the_count():
    with pytest.raises(ValueError, match='shard_index'):
        FuserConfig(shard_count=2, shard_index=2)
