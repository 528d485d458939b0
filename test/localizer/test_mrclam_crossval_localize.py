"""landmark_mrclam --cross-validate --modes localize on the first 60 s of dataset 6."""

from pathlib import Path

from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.mrclam import crossval
from landmark_ros.mrclam.config import load_config
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.localize import Track
from landmark_ros.mrclam.localize_data import load_all_extras
import numpy as np
import pytest
from test_mrclam_localize import _first_seconds, DATASET, KEYS


def test_in_window_keeps_the_stamps_of_the_evaluated_part():
    times = np.arange(10.0)
    track = Track(3, times, np.zeros((10, 3)), np.tile(np.eye(3), (10, 1, 1)),
                  np.zeros((10, 3)), {})
    cut = crossval._in_window(track, (2.0, 5.0))
    np.testing.assert_array_equal(cut.times, [2.0, 3.0, 4.0])
    assert cut.x.shape == (3, 3) and cut.P.shape == (3, 3, 3) and cut.truth.shape == (3, 3)


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
@pytest.mark.parametrize('scheme', ['halves', 'robots'])
def test_each_fold_localizes_with_its_own_calibration(scheme):
    dataset = load_dataset(DATASET)
    dataset, extras = _first_seconds(dataset, load_all_extras(dataset), 60.0, (3, 5))
    config = load_config(Path(__file__).resolve().parents[2] / 'config' / 'mrclam.yaml')
    base = LocalizerConfig(odometry_alphas=(2.0, 6.8, 1.6, 0.26),
                           initial_stddev=(0.02, 0.02, 0.02))
    entries = crossval.cross_validate_localize(dataset, extras, config, (base, 0.175),
                                               ['localize'], scheme)
    assert len(entries) == 2
    for entry in entries:
        assert KEYS <= set(entry) and entry['map'] == 'surveyed'
        assert np.isfinite(entry['anees']) and entry['position_rmse_m'] < 0.5
        assert entry['calibration']['range_scale_coeffs'][2] < 0.0
    first, second = (e['calibration'] for e in entries)
    assert first['range_scale_coeffs'] != second['range_scale_coeffs']
    if scheme == 'robots':   # the left-out robot alone
        assert [[r['robot'] for r in e['robots']] for e in entries] == [[3], [5]]
    else:
        assert all([r['robot'] for r in e['robots']] == [3, 5] for e in entries)
