"""``python -m landmark_ros.demo --localize``: the team localizes against the fused map."""

import re

from test_demo import assert_nothing_left, domain_of, port_files, run_demo


def _localized_run(tmp_path, mode):
    """Run 8 s of the demo with ``mode``; return its output and the localization rows."""
    ports_before = set().union(*(port_files(d) for d in range(150, 200)))
    code, output, children, shm = run_demo(
        tmp_path, '--duration', '8', '--landmarks', '12', '--seed', '3', mode, '--no-plot')
    assert code == 0, output
    match = re.search(r'Localization on wheel odometry against the fused map \(poses '
                      r'robot 1: (\d+), robot 2: (\d+), robot 3: (\d+)[;)]', output)
    assert match, output
    assert all(int(n) >= 100 for n in match.groups()), output  # 20 Hz for 8 s
    rows = re.findall(r'^fused \(live\)\s+False\s+(\S+)\s+(\d+\.\d+)\s+(\d+\.\d+)\s+'
                      r'(\d+\.\d+)\s+(\d+\.\d+)\s+(\d+)\s+(\d+)', output, re.M)
    assert [r[0] for r in rows] == ['1', '2', '3', 'all'], output
    modules = sorted(re.search(r'-m (\S+)', cmd).group(1) for cmd in children.values())
    assert modules.count('landmark_ros.nodes.localizer') == 3, children
    assert_nothing_left(children, shm, domain_of(output), ports_before)
    return output, rows


def test_short_demo_run_localizes_every_robot_on_odometry(tmp_path):
    output, rows = _localized_run(tmp_path, '--localize')
    for robot, rmse, _, anees, inside, used, _ in rows:
        assert float(rmse) < 0.5, output  # odometry alone drifts further
        assert int(used) > 0 or robot == 'all', output
    overall = rows[-1]
    assert 0.5 < float(overall[3]) < 6.0 and float(overall[4]) > 0.8, output


def test_short_slam_demo_scores_the_localizers_that_pose_the_observers(tmp_path):
    # The localizers' own pose topic (what the observers take) is scored.
    output, rows = _localized_run(tmp_path, '--slam')
    assert all(float(row[1]) < 0.8 for row in rows), output
    assert "--slam: the map's average NEES is not judged here" in output
    assert re.search(r'^OK: all \d+ measured landmarks fused \(split_covariance', output,
                     re.M), output
