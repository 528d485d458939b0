"""landmark_mrclam --sensor range|bearing --through-nodes on the synthetic dataset."""

import json

from landmark_ros.mrclam.cli import main
import numpy as np
import pytest
from test_mrclam import CONFIG, LANDMARKS, noisy_dataset  # noqa: F401, the fixture

MEAN_TOLERANCE_M = 1e-5
"""Through the nodes vs offline, per landmark mean (the fusers take the same views).

Usually 1e-15; once in CI (bearing) 1.0e-6 m with the covariance 6e-6 off, same views and
counts, not reproduced in twelve runs here, loaded or not (cause not found). A node path
that fused other views or another pipeline would be millimetres off."""


# Range-only is left out: on this synthetic data (a metre of straight line per robot) the
# curvature rule places no range-only landmark, so there is no map to compare.
@pytest.mark.parametrize('sensor', ['bearing'])
def test_partial_sensor_through_nodes_agrees_with_offline(noisy_dataset, tmp_path,  # noqa: F811
                                                          sensor):
    directory, _ = noisy_dataset
    offline_json, nodes_json = tmp_path / 'offline.json', tmp_path / 'nodes.json'
    common = [str(directory), '--config', str(CONFIG), '--sensor', sensor,
              '--fusion', 'split_covariance_intersection']
    assert main(common + ['--json', str(offline_json)]) == 0
    code = main(common + ['--through-nodes', '--no-progress', '--json', str(nodes_json)])
    document = json.loads(nodes_json.read_text())
    assert code == 0, document.get('agreement')
    assert document['mode'] == 'through_nodes'
    (entry,) = document['agreement'].values()
    assert entry['same_ids'] and entry['same_counts'], entry
    assert entry['max_mean_diff_m'] < MEAN_TOLERANCE_M, entry
    nodes = document['nodes']
    assert not nodes['cloud_mismatch']
    # Partial rows only: no landmark rows out, every placement from partial observations.
    assert nodes['rows_out'] == 0 and nodes['partial_rows_out'] > 0
    (offline,) = json.loads(offline_json.read_text())['summary']
    (summary,) = document['summary']
    assert summary['sensor'] == offline['sensor'] == sensor
    assert summary['landmarks_initialised'] == offline['landmarks_initialised'] > 0
    assert sorted(lm['id'] for lm in summary['landmarks']) == sorted(
        lm['id'] for lm in offline['landmarks'])
    assert {lm['id'] for lm in summary['landmarks']} <= set(LANDMARKS)
    assert np.isfinite(summary['rmse_m'])


def test_partial_cloud_has_no_dropped_column():
    from landmark_ros.mrclam.player import stamped_messages
    ids, z = np.array([3, 4]), np.array([[1.0, 0.5], [2.0, -0.5]])
    for sensor, kept in (('range', 0), ('bearing', 1)):
        _, cloud = stamped_messages(10, 'cam', np.zeros(3), np.eye(3), ids, z, sensor)
        names = [f.name for f in cloud.fields]
        assert names == ['id', sensor]
        from landmark_ros.ros.cloud import read_columns
        from landmark_ros.ros.schemas import OBSERVATION_FIELDS
        columns = read_columns(cloud, OBSERVATION_FIELDS)
        assert columns['id'].tolist() == [3, 4]
        assert columns[sensor].tolist() == z[:, kept].tolist()
        assert 'range' not in columns or 'bearing' not in columns
