"""landmark_mrclam --cross-validate and the parts of a dataset."""

import json

from landmark_ros.mrclam import crossval
from landmark_ros.mrclam.calibrate import calibrate, OBSERVER_FIELDS
from landmark_ros.mrclam.cli import main
from landmark_ros.mrclam.config import load_config
from landmark_ros.mrclam.data import load_dataset, Part
import numpy as np
import pytest
from test_mrclam import CONFIG, make_dataset, noisy_dataset  # noqa: F401, the fixture

S = 1_000_000_000


def test_parts_split_the_sightings(noisy_dataset):  # noqa: F811
    dataset = load_dataset(noisy_dataset[0])
    total = sum(len(r.times) for r in dataset.robots)
    first, second = (fold.calibrate_on for fold in crossval.folds(dataset))
    a, b = dataset.part(first), dataset.part(second)
    assert sum(len(r.times) for r in a.robots) + sum(len(r.times) for r in b.robots) == total
    assert max(r.times.max() for r in a.robots) < min(r.times.min() for r in b.robots)
    only = dataset.part(Part(robots=(dataset.robots[1].number,)))
    assert [r.number for r in only.robots] == [dataset.robots[1].number]
    np.testing.assert_array_equal(only.robots[0].z, dataset.robots[1].z)
    for robot in a.robots:      # rows stay aligned
        assert len(robot.ids) == len(robot.z) == len(robot.poses) == len(robot.times)


def test_folds_calibrate_and_evaluate_on_disjoint_parts(noisy_dataset):  # noqa: F811
    dataset = load_dataset(noisy_dataset[0])
    halves = crossval.folds(dataset, 'halves')
    assert [f.calibrate_on for f in halves] == [f.evaluate_on for f in halves[::-1]]
    robots = crossval.folds(dataset, 'robots')
    assert len(robots) == len(dataset.robots)
    for fold in robots:
        assert not set(fold.calibrate_on.robots) & set(fold.evaluate_on.robots)
    with pytest.raises(ValueError):
        crossval.folds(dataset, 'thirds')


def test_calibrated_config_takes_every_estimated_value(noisy_dataset):  # noqa: F811
    dataset = load_dataset(noisy_dataset[0])
    calibration = calibrate(dataset, part=Part(end_s=dataset.duration / 2))
    config = crossval.calibrated_config(load_config(CONFIG), calibration)
    for name in OBSERVER_FIELDS:
        assert getattr(config.observer, name) == pytest.approx(getattr(calibration, name))
    # The part matters: the other half gives other values.
    other = calibrate(dataset, part=Part(start_s=dataset.duration / 2))
    assert other.range_stddev != calibration.range_stddev


def test_cross_validate_prints_and_writes_every_fold_and_mode(
        noisy_dataset, tmp_path, capsys):  # noqa: F811
    out = tmp_path / 'cv.json'
    assert main([str(noisy_dataset[0]), '--cross-validate', '--modes', 'ids', 'hide_ids',
                 '--json', str(out)]) == 0
    printed = capsys.readouterr().out
    entries = json.loads(out.read_text())['cross_validation']
    assert [(e['fold'], e['mode']) for e in entries] == [
        ('first->second', 'ids'), ('first->second', 'hide_ids'),
        ('second->first', 'ids'), ('second->first', 'hide_ids')]
    dataset = load_dataset(noisy_dataset[0])
    for entry in entries:
        assert entry['fusion'] == 'split_covariance_intersection'
        assert entry['fold'] in printed
        assert entry['rmse_m'] < 0.1 and entry['anees_interval'][0] < entry['anees_interval'][1]
        fold = {f.name: f for f in crossval.folds(dataset)}[entry['fold']]
        expected = calibrate(dataset, part=fold.calibrate_on).observer_values()
        for name, value in expected.items():
            np.testing.assert_allclose(np.ravel(entry['calibration'][name]), np.ravel(value),
                                       rtol=1e-9)
        if entry['mode'] == 'hide_ids':
            assert 0.0 <= entry['association_accuracy'] <= 1.0
            assert entry['tracks_confirmed'] >= 1
        # config/mrclam.yaml turns change detection on: its alarms are reported.
        assert 0 <= entry['move_alarms'] <= entry['move_tested_rows']
        assert 0 < entry['move_tested_rows'] <= (entry['observations_used']
                                                 + entry['observations_rejected'])
        assert f"moved {entry['move_alarms']}/{entry['move_tested_rows']}" in printed
    # Each fold fused only the rows of its evaluated half.
    evaluated = {e['fold']: e['observations_used'] + e['observations_rejected']
                 for e in entries if e['mode'] == 'ids'}
    halves = crossval.folds(dataset)
    for fold in halves:
        rows = sum(len(r.times) for r in dataset.part(fold.evaluate_on).robots)
        assert evaluated[fold.name] <= rows
