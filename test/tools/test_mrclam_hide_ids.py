"""landmark_mrclam --hide-ids on the synthetic dataset of test_mrclam (offline)."""

import json

from landmark_ros.mrclam.cli import main
from test_mrclam import CONFIG, LANDMARKS, noisy_dataset  # noqa: F401, the fixture


def test_hide_ids_associates_the_sightings_and_reports_it(noisy_dataset, tmp_path,  # noqa: F811
                                                          capsys):
    directory, info = noisy_dataset
    out = tmp_path / 'result.json'
    assert main([str(directory), '--config', str(CONFIG), '--hide-ids', '--fusion',
                 'split_covariance_intersection', '--json', str(out)]) == 0
    assert '== association (IDs hidden)' in capsys.readouterr().out
    (entry,) = json.loads(out.read_text())['summary']
    assert entry['true_landmarks'] == len(LANDMARKS)
    assert entry['tracks_confirmed'] == len(LANDMARKS)
    assert entry['association_accuracy'] >= entry['oracle_accuracy'] - 0.02
    assert entry['gospa_m'] < 0.1 and entry['rmse_m'] < 0.05
    assert sorted(lm['id'] for lm in entry['landmarks']) == sorted(LANDMARKS)


def test_hide_ids_through_nodes_is_refused(noisy_dataset, capsys):  # noqa: F811
    directory, _ = noisy_dataset
    assert main([str(directory), '--config', str(CONFIG), '--hide-ids',
                 '--through-nodes']) == 2
    assert 'offline only' in capsys.readouterr().err
