"""The landmarks' apparent offsets (``mrclam.landmark_offsets``, ``--calibrate``)."""

from collections import Counter
import json
from pathlib import Path

from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.mrclam import cli
from landmark_ros.mrclam.data import Dataset, Robot
from landmark_ros.mrclam.landmark_offsets import apparent_offsets, format_offsets
import numpy as np
import pytest
from test_camera_delay import LANDMARKS, moving_pose

SEEN_AT = {6: (0.02, -0.01), 7: (-0.015, 0.0), 8: (0.0, 0.02), 9: (0.01, 0.01),
           10: (-0.02, -0.015)}
"""Offset of where the camera sees each landmark from its surveyed position [m]."""
DATASET6 = Path(__file__).resolve().parents[3] / 'shared' / 'data' / 'mrclam' / 'dataset6'


def _dataset(seen_at=SEEN_AT, persistent=True, noise=0.02, seed=0):
    """
    Sightings from the true poses of landmarks seen ``seen_at`` off [m], noise ``noise``.

    Not ``persistent``: the second half of the run sees the opposite offsets. The
    first row of each robot is a misreading 50 m away.
    """
    rng = np.random.default_rng(seed)
    robots = []
    for number in (1, 2, 3):
        stamps = np.repeat(np.arange(0.0, 60.0, 0.2) + 0.01 * number, len(LANDMARKS))
        ids = np.tile(np.array(sorted(LANDMARKS)), len(stamps) // len(LANDMARKS))
        pose = moving_pose(number, stamps)
        sign = np.ones(len(ids)) if persistent else np.where(stamps < 30.0, 1.0, -1.0)
        seen = (np.array([LANDMARKS[i] for i in ids.tolist()])
                + sign[:, None] * np.array([seen_at[i] for i in ids.tolist()]))
        d = seen - pose[:, :2] + rng.normal(0.0, noise, (len(ids), 2))
        z = np.stack([np.hypot(d[:, 0], d[:, 1]),
                      wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2])], axis=1)
        z[0] = [50.0, 0.0]
        robots.append(Robot(number, stamps, ids, z, pose, stamps, pose, Counter()))
    return Dataset(Path('synthetic'), robots, dict(LANDMARKS), {}, {})


def test_offsets_that_persist_are_found_per_landmark_and_in_both_halves():
    result = apparent_offsets(_dataset())
    assert [e['id'] for e in result['landmarks']] == sorted(LANDMARKS)
    for entry in result['landmarks']:
        true = np.array(SEEN_AT[entry['id']])
        se = np.array(entry['stderr_m'])
        assert 0.0 < se.max() < 0.003
        np.testing.assert_allclose(entry['offset_m'], true, atol=4 * se.max())
        np.testing.assert_allclose(entry['first_half_m'], true, atol=6 * se.max())
        np.testing.assert_allclose(entry['second_half_m'], true, atol=6 * se.max())
    rms = np.sqrt(np.mean(np.square(list(SEEN_AT.values())), axis=0))
    np.testing.assert_allclose(result['rms_m'], rms, atol=0.002)
    assert np.all(np.array(result['excess_rms_m']) <= np.array(result['rms_m']))
    assert min(result['halves_correlation']) > 0.9
    assert result['rows_left_out'] == 3            # one misreading per robot
    assert 'RMS' in format_offsets(result)


def test_offsets_that_flip_between_halves_do_not_correlate():
    result = apparent_offsets(_dataset(persistent=False))
    # Each half sees the opposite offset: the whole-run means are near zero and the
    # halves anti-correlated, which is no persistent offset.
    assert max(result['rms_m']) < 0.004
    assert max(result['halves_correlation']) < -0.9


def test_without_noise_and_offsets_nothing_is_left_and_few_landmarks_give_no_summary():
    result = apparent_offsets(_dataset(dict.fromkeys(SEEN_AT, (0.0, 0.0)), noise=0.0))
    assert max(result['rms_m']) < 1e-9
    sparse = apparent_offsets(_dataset(), min_rows=10_000)
    assert sparse['landmarks'] == [] and np.isnan(sparse['rms_m']).all()


@pytest.mark.skipif(not DATASET6.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_calibrate_prints_and_writes_the_offsets(tmp_path, capsys):
    out = tmp_path / 'cal.json'
    assert cli.main([str(DATASET6), '--calibrate', '--json', str(out)]) == 0
    assert "landmarks' apparent offsets" in capsys.readouterr().out
    offsets = json.loads(out.read_text())['landmark_offsets']
    assert len(offsets['landmarks']) == 15
    assert 0.0 < max(offsets['excess_rms_m']) < 0.05
