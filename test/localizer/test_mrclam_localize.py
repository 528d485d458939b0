"""The MRCLAM localization replay on the first 60 s of dataset 6 (skipped without it)."""

import dataclasses
from pathlib import Path

from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.mrclam import localize
from landmark_ros.mrclam.data import load_dataset
from landmark_ros.mrclam.localize_data import load_all_extras
import numpy as np
import pytest

DATASET = Path(__file__).resolve().parents[3] / 'shared' / 'data' / 'mrclam' / 'dataset6'
KEYS = {'position_rmse_m', 'heading_rmse_rad', 'anees', 'inside_95_fraction'}


def _first_seconds(dataset, extras, seconds, numbers):
    start = min(r.gt_times[0] for r in dataset.robots)
    robots = []
    for r in dataset.robots:
        if r.number not in numbers:
            continue
        k = r.times < start + seconds
        g = r.gt_times < start + seconds + 1.0
        robots.append(dataclasses.replace(r, times=r.times[k], ids=r.ids[k], z=r.z[k],
                                          poses=r.poses[k], gt_times=r.gt_times[g],
                                          gt_poses=r.gt_poses[g]))
        e = extras[r.number]
        o, s = e.odom_times < start + seconds, e.sighting_times < start + seconds
        extras[r.number] = dataclasses.replace(
            e, odom_times=e.odom_times[o], odom_twist=e.odom_twist[o],
            sighting_times=e.sighting_times[s], sighting_robot=e.sighting_robot[s],
            sighting_z=e.sighting_z[s])
    return dataclasses.replace(dataset, robots=robots), extras


@pytest.mark.skipif(not DATASET.is_dir(), reason='needs ../shared MRCLAM dataset 6')
def test_localization_beats_dead_reckoning_and_reports_the_issue_keys():
    dataset = load_dataset(DATASET)
    dataset, extras = _first_seconds(dataset, load_all_extras(dataset), 60.0, (3, 5))
    config = LocalizerConfig(odometry_alphas=(2.0, 6.8, 1.6, 0.26), range_stddev=0.04,
                             range_stddev_per_m=0.05, bearing_stddev=0.017,
                             initial_stddev=(0.02, 0.02, 0.02))
    entries, tracks = localize.run_all(dataset, extras, config,
                                       {'surveyed': localize.surveyed_map(dataset)}, 0.175)
    by = {(e['map'], e['cooperative']): e for e in entries}
    floor, surveyed = by[('dead_reckoning', False)], by[('surveyed', False)]
    assert surveyed['position_rmse_m'] < floor['position_rmse_m']
    assert surveyed['rows_used'] > 0 and by[('surveyed', True)]['robot_rows_used'] > 0
    for entry in entries:
        assert KEYS <= set(entry) and {'map', 'cooperative', 'robots'} <= set(entry)
        assert [r['robot'] for r in entry['robots']] == [3, 5]
        assert all(KEYS <= set(r) and np.isfinite(r['anees']) for r in entry['robots'])
    assert len(localize.targets(entries)) == 5
