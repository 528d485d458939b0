"""Tests of fuser.map_file: versioned JSON, atomic save, load checks, move_aside."""

import datetime
import json
import os

from landmark_ros.fuser import map_file
from landmark_ros.fuser.map_file import MapFileError
from landmark_ros.fusion.landmark_map import LandmarkMap
import numpy as np
import pytest

NOW = datetime.datetime(2024, 3, 5, 7, 8, 9, tzinfo=datetime.timezone.utc)


def example_map(rng):
    """Return a LandmarkMap with a few confirmed landmarks (awkward floats included)."""
    lm = LandmarkMap('split_covariance_intersection', min_observations=1)
    count = 6
    A = rng.standard_normal((count, 2, 2))
    R = A @ np.swapaxes(A, 1, 2) * 0.1 + 0.01 * np.eye(2)
    ids = np.array([0, 3, 17, 2 ** 20 + 1, 2 ** 32 - 1, 9], np.int64)
    lm.update(ids, rng.uniform(-1e3, 1e3, (count, 2)) / 3.0, R, 0.3 * R,
              source=['a', 'b', 'a', 'c', 'b', 'a'],
              stamp_ns=np.arange(count) * 100_000_000 + 1_000_000_000_000)
    lm.update(ids[:3], lm.snapshot()[1][:3] + 1e-3, R[:3], 0.3 * R[:3], source='d',
              stamp_ns=2_000_000_000_000)
    return lm


def files_in(directory):
    return sorted(os.listdir(directory))


def test_save_then_load_round_trip(tmp_path, rng):
    lm = example_map(rng)
    path = str(tmp_path / 'map.json')
    records = lm.to_records()
    map_file.save(path, records, 'map', lm.fusion)
    document = map_file.load(path, 'map')
    assert document['landmarks'] == records     # floats survive JSON exactly
    assert document['fusion'] == 'split_covariance_intersection'
    saved_at = datetime.datetime.fromisoformat(document['saved_at'])
    assert saved_at.tzinfo is not None
    assert abs((datetime.datetime.now(datetime.timezone.utc) - saved_at).total_seconds()) < 60
    loaded = LandmarkMap('split_covariance_intersection')
    loaded.load_records(document['landmarks'])
    assert loaded.to_records() == records
    for a, b in zip(loaded.snapshot(), lm.snapshot()):
        np.testing.assert_allclose(a, b, rtol=1e-15, atol=0)
    assert files_in(tmp_path) == ['map.json']


def test_file_is_plain_json_with_the_documented_keys(tmp_path, rng):
    lm = example_map(rng)
    path = tmp_path / 'map.json'
    map_file.save(str(path), lm.to_records(), 'odom', 'independent')
    text = path.read_text()
    assert text.endswith('\n')
    document = json.loads(text)
    assert set(document) == {'format', 'version', 'saved_at', 'world_frame', 'fusion',
                             'landmarks'}
    assert document['format'] == 'landmark_ros/map' == map_file.FORMAT
    assert document['version'] == 1 == map_file.VERSION
    assert document['world_frame'] == 'odom' and document['fusion'] == 'independent'
    assert isinstance(document['landmarks'], list) and len(document['landmarks']) == len(lm)
    assert {'id', 'mean', 'covariance', 'covariance_dependent', 'observations',
            'sources'} <= set(document['landmarks'][0])


def test_empty_map_round_trip(tmp_path):
    path = str(tmp_path / 'map.json')
    map_file.save(path, [], 'map', 'independent')
    assert map_file.load(path, 'map')['landmarks'] == []


def test_save_replaces_an_existing_file(tmp_path, rng):
    path = str(tmp_path / 'map.json')
    map_file.save(path, [{'id': 1}], 'map', 'independent')
    records = example_map(rng).to_records()
    map_file.save(path, records, 'map', 'independent')
    assert map_file.load(path, 'map')['landmarks'] == records
    assert files_in(tmp_path) == ['map.json']


def _write(path, document):
    path.write_text(json.dumps(document))


def _valid_document():
    return {'format': map_file.FORMAT, 'version': map_file.VERSION, 'saved_at': 'x',
            'world_frame': 'map', 'fusion': 'independent', 'landmarks': []}


@pytest.mark.parametrize('change, message', [
    ({'version': 2}, 'version 2, expected 1'),
    ({'version': '1'}, "version '1', expected 1"),
    ({'version': None}, 'version None'),
    ({'format': 'other/map'}, 'not a landmark_ros/map file'),
    ({'format': None}, 'not a landmark_ros/map file'),
    ({'world_frame': 'odom'}, "map in frame 'odom', expected 'map'"),
    ({'landmarks': {}}, 'no landmark list'),
    ({'landmarks': None}, 'no landmark list'),
])
def test_load_rejects_wrong_documents(tmp_path, change, message):
    path = tmp_path / 'map.json'
    _write(path, dict(_valid_document(), **change))
    with pytest.raises(MapFileError, match=message):
        map_file.load(str(path), 'map')
    assert isinstance(MapFileError('x'), ValueError)


def test_load_rejects_missing_keys(tmp_path):
    for key in ('format', 'version', 'world_frame', 'landmarks'):
        document = _valid_document()
        del document[key]
        _write(tmp_path / 'map.json', document)
        with pytest.raises(MapFileError):
            map_file.load(str(tmp_path / 'map.json'), 'map')


@pytest.mark.parametrize('text', ['', '{', '[1, 2]', '"text"', 'null', '{"format": ',
                                  'not json at all'])
def test_load_rejects_truncated_or_foreign_json(tmp_path, text):
    path = tmp_path / 'map.json'
    path.write_text(text)
    with pytest.raises(MapFileError):
        map_file.load(str(path), 'map')


def test_load_rejects_a_truncated_real_file(tmp_path, rng):
    path = tmp_path / 'map.json'
    map_file.save(str(path), example_map(rng).to_records(), 'map', 'independent')
    text = path.read_text()
    for cut in (len(text) // 3, len(text) - 3):
        path.write_text(text[:cut])
        with pytest.raises(MapFileError, match='not valid JSON'):
            map_file.load(str(path), 'map')


def test_load_missing_file_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        map_file.load(str(tmp_path / 'absent.json'), 'map')


def test_move_aside_renames_with_a_timestamp(tmp_path):
    path = tmp_path / 'map.json'
    path.write_text('first')
    target = map_file.move_aside(str(path), now=NOW)
    assert target == f'{path}.bad-20240305T070809Z'
    assert not path.exists() and (tmp_path / 'map.json.bad-20240305T070809Z').read_text() == \
        'first'
    # A second bad file in the same second does not overwrite the first.
    path.write_text('second')
    assert map_file.move_aside(str(path), now=NOW) == f'{path}.bad-20240305T070809Z-1'
    path.write_text('third')
    assert map_file.move_aside(str(path), now=NOW) == f'{path}.bad-20240305T070809Z-2'
    assert (tmp_path / 'map.json.bad-20240305T070809Z').read_text() == 'first'
    assert (tmp_path / 'map.json.bad-20240305T070809Z-1').read_text() == 'second'
    assert (tmp_path / 'map.json.bad-20240305T070809Z-2').read_text() == 'third'
    assert files_in(tmp_path) == ['map.json.bad-20240305T070809Z',
                                  'map.json.bad-20240305T070809Z-1',
                                  'map.json.bad-20240305T070809Z-2']


def test_move_aside_defaults_to_the_current_utc_time(tmp_path):
    path = tmp_path / 'map.json'
    path.write_text('x')
    before = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    target = map_file.move_aside(str(path))
    after = datetime.datetime.now(datetime.timezone.utc)
    stamp = target.rsplit('.bad-', 1)[1]
    when = datetime.datetime.strptime(stamp, '%Y%m%dT%H%M%SZ').replace(
        tzinfo=datetime.timezone.utc)
    assert before <= when <= after and os.path.exists(target)


def test_move_aside_missing_file_raises(tmp_path):
    with pytest.raises(FileNotFoundError):
        map_file.move_aside(str(tmp_path / 'absent.json'), now=NOW)


@pytest.mark.parametrize('failure', ['json.dump', 'os.replace', 'os.fsync'])
def test_failed_save_leaves_the_previous_file_and_no_temporary(tmp_path, rng, monkeypatch,
                                                               failure):
    path = tmp_path / 'map.json'
    old_records = [{'id': 1, 'mean': [0.5, 0.25]}]
    map_file.save(str(path), old_records, 'map', 'independent')
    old_text = path.read_text()
    real_dump = json.dump

    def dump_half_then_fail(document, stream, **kwargs):
        real_dump(document, stream, **kwargs)   # the whole new document is written ...
        stream.flush()
        raise OSError('disk full')              # ... but the save does not complete

    def fail(*args, **kwargs):
        raise OSError('simulated failure')

    if failure == 'json.dump':
        monkeypatch.setattr(map_file.json, 'dump', dump_half_then_fail)
    elif failure == 'os.replace':
        monkeypatch.setattr(map_file.os, 'replace', fail)
    else:
        monkeypatch.setattr(map_file.os, 'fsync', fail)
    with pytest.raises(OSError):
        map_file.save(str(path), example_map(rng).to_records(), 'map', 'independent')
    monkeypatch.undo()
    assert path.read_text() == old_text
    assert map_file.load(str(path), 'map')['landmarks'] == old_records
    assert files_in(tmp_path) == ['map.json']


def test_failed_first_save_leaves_nothing(tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise TypeError('not serialisable')

    monkeypatch.setattr(map_file.json, 'dump', fail)
    with pytest.raises(TypeError):
        map_file.save(str(tmp_path / 'map.json'), [], 'map', 'independent')
    assert files_in(tmp_path) == []


def test_interrupted_save_leaves_no_temporary(tmp_path, monkeypatch):
    # Even a KeyboardInterrupt midway cleans up (BaseException).
    path = tmp_path / 'map.json'
    map_file.save(str(path), [], 'map', 'independent')

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(map_file.os, 'replace', interrupt)
    with pytest.raises(KeyboardInterrupt):
        map_file.save(str(path), [{'id': 2}], 'map', 'independent')
    monkeypatch.undo()
    assert files_in(tmp_path) == ['map.json']
    assert map_file.load(str(path), 'map')['landmarks'] == []


def test_temporary_file_is_in_the_same_directory(tmp_path, monkeypatch):
    # Same directory: os.replace is a rename on one file system, hence atomic.
    seen = []
    real_replace = os.replace

    def spy(source, target):
        seen.append((source, target))
        return real_replace(source, target)

    monkeypatch.setattr(map_file.os, 'replace', spy)
    path = tmp_path / 'sub' / 'map.json'
    path.parent.mkdir()
    map_file.save(str(path), [], 'map', 'independent')
    (source, target), = seen
    assert os.path.dirname(source) == str(path.parent) and target == str(path)
    assert os.path.basename(source).startswith('.map.json.') and source.endswith('.tmp')


def test_save_into_a_missing_directory_raises(tmp_path):
    with pytest.raises(OSError):
        map_file.save(str(tmp_path / 'absent' / 'map.json'), [], 'map', 'independent')
