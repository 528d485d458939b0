"""
``ros2 launch landmark_ros team.launch.py`` from a colcon-built workspace, with the real tools.

The simulated demo fuses a map and stops on Ctrl-C leaving nothing; a bearing-only robot
among four with names of the user's is fused; ``rviz:=true`` without rviz2 and a missing
parameter file fail with one line before anything starts. Skipped without ``../shared``.
"""

import re
import warnings

from diagnostic_msgs.msg import DiagnosticArray
from landmark_ros.ros.qos import LATCHED
from landmark_ros.ros.schemas import read_landmarks
from launch_rig import build_workspace, Launch, require_tools, teardown_hangs
import pytest
from rosutil import Collector, next_domain_id, RosEnv
from sensor_msgs.msg import PointCloud2
import yaml

pytestmark = pytest.mark.slow

MAP_DEADLINE_S = 240.0
"""Wall time a team has to publish a fused map: starting five Python nodes on a busy
two-core machine takes tens of seconds."""

STOP_DEADLINE_S = 60.0
"""Wall time for a launch to end after Ctrl-C, or to fail on a bad argument."""

FAILED_CHECK_DEADLINE_S = 60.0


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    """Build a colcon workspace holding the package; return its install directory."""
    require_tools()
    return build_workspace(tmp_path_factory.mktemp('launch_ws'))


def launch(install, tmp_path, *arguments):
    """Return a started ``Launch`` in a fresh domain."""
    return Launch(install, list(arguments), next_domain_id(), tmp_path / 'launch.log')


def fused_count(messages):
    """Return the landmark count of the latest fused map received (0 before any)."""
    return len(read_landmarks(messages[-1]).ids) if messages else 0


def stop_cleanly(team):
    """
    Ctrl-C the launch; check it ends with code 0, escalating no signal, leaving nothing.

    Every process finishes cleanly, except one the node's watchdog ended inside DDS's
    participant deletion (``launch_rig.teardown_hangs``), which is reported as a warning.
    """
    team.interrupt()
    code = team.wait(STOP_DEADLINE_S)
    output = team.output()
    assert code == 0, f'ros2 launch did not end cleanly on SIGINT ({code}):\n{output[-3000:]}'
    assert 'SIGTERM' not in output and 'SIGKILL' not in output, output[-3000:]
    started = len(re.findall(r'process started with pid', output))
    assert started
    hung = teardown_hangs(output)
    if hung:
        warnings.warn(f'DDS teardown hung in {sorted(hung)}; the stop watchdog ended it')
    assert len(re.findall(r'process has finished cleanly', output)) + len(hung) == started, \
        output[-3000:]
    assert team.left_running() == []


def test_sim_demo_fuses_a_map_and_stops_on_ctrl_c(install, tmp_path):
    with launch(install, tmp_path, 'sim:=true') as team:
        env = RosEnv(domain_id=team.domain_id)
        try:
            node = env.node('watcher')
            maps = Collector(node, PointCloud2, '/fused_landmarks', LATCHED)
            assert env.spin_until(lambda: fused_count(maps.messages) >= 10 or
                                  team.popen.poll() is not None, MAP_DEADLINE_S)
            assert fused_count(maps.messages) >= 10, team.output()[-3000:]
        finally:
            env.close()
        stop_cleanly(team)


def partial_fused(statuses, robot):
    """Return the partial observations of ``robot`` the fuser fused (its diagnostics)."""
    best = 0
    for status in statuses:
        if f'/{robot}/' not in status.name or status.name.endswith(f'/{robot}/landmarks'):
            continue
        values = {pair.key: pair.value for pair in status.values}
        for key in ('partial_fused', 'views_fused'):
            if values.get(key, '0').isdigit():
                best = max(best, int(values.get(key, '0')))
    return best


def test_bearing_only_robot_among_four_named_robots_is_fused(install, tmp_path):
    sim = yaml.safe_load((install / 'landmark_ros/share/landmark_ros/config/sim.yaml')
                         .read_text())
    sim['/**/landmark_sim']['ros__parameters']['sensor_kinds'] = ['rb', 'rb', 'rb', 'bearing']
    sim_params = tmp_path / 'sim.yaml'
    sim_params.write_text(yaml.safe_dump(sim))
    with launch(install, tmp_path, 'sim:=true', 'robots:=alpha beta gamma delta',
                f'sim_params:={sim_params}') as team:
        env = RosEnv(domain_id=team.domain_id)
        try:
            node = env.node('watcher')
            statuses = []
            node.create_subscription(DiagnosticArray, '/diagnostics',
                                     lambda msg: statuses.extend(msg.status), 100)
            landmarks = Collector(node, PointCloud2, '/delta/landmarks')
            assert env.spin_until(lambda: partial_fused(statuses, 'delta') > 0 or
                                  team.popen.poll() is not None, MAP_DEADLINE_S), \
                team.output()[-3000:]
            assert partial_fused(statuses, 'delta') > 0, team.output()[-3000:]
            # The bearing-only robot publishes no complete landmark rows.
            assert all(read_landmarks(msg).ids.size == 0 for msg in landmarks.messages)
        finally:
            env.close()
        stop_cleanly(team)


def check_failed_before_start(team, expected):
    """Check the launch failed with one error line matching ``expected``, nothing started."""
    code = team.wait(FAILED_CHECK_DEADLINE_S)
    output = team.output()
    assert code not in (None, 0), output
    errors = [line for line in output.splitlines() if '[ERROR]' in line]
    assert len(errors) == 1 and re.search(expected, errors[0]), output
    assert 'process started' not in output, output
    assert team.left_running(grace_s=0.0) == []


def test_rviz_without_rviz2_fails_in_one_line_and_starts_nothing(install, tmp_path):
    with launch(install, tmp_path, 'rviz:=true', 'sim:=true') as team:
        check_failed_before_start(team, r"rviz: package 'rviz2' is not installed")


@pytest.mark.parametrize('argument', ['observer_params', 'fuser_params', 'sim_params'])
def test_missing_params_file_fails_before_anything_starts(install, tmp_path, argument):
    missing = tmp_path / 'missing.yaml'
    with launch(install, tmp_path, 'sim:=true', f'{argument}:={missing}') as team:
        check_failed_before_start(team, rf'{argument}: no such parameter file: {missing}')


def test_unknown_fusion_method_fails_before_anything_starts(install, tmp_path):
    with launch(install, tmp_path, 'fusion:=average') as team:
        check_failed_before_start(team, r"fusion: 'average' is not one of .*"
                                        r'covariance_intersection')


def test_bad_precision_sources_fail_before_anything_starts(install, tmp_path):
    observer = yaml.safe_load((install / 'landmark_ros/share/landmark_ros/config/observer.yaml')
                              .read_text())
    observer['/**/landmark_observer']['ros__parameters']['precision_sources'] = 'four'
    path = tmp_path / 'observer.yaml'
    path.write_text(yaml.safe_dump(observer))
    with launch(install, tmp_path, f'observer_params:={path}') as team:
        check_failed_before_start(team, 'observer_params: precision_sources must be an '
                                        "integer from 1 to 16, got 'four'")
