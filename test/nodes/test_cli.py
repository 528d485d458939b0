"""The console scripts as users run them: --help, command-line errors, exit codes."""

from dataclasses import fields
import os
from pathlib import Path
import subprocess
import sys

from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.sim.simulation import SimConfig
import pytest
from rosutil import next_domain_id

BIN = Path(sys.executable).parent
SCRIPTS = {
    'landmark_observer': (ObserverConfig, ['pose', 'observations', 'landmarks', 'odometry']),
    'landmark_fuser': (FuserConfig, ['input_topics', 'fused_landmarks', 'fused_markers']),
    'landmark_sim': (SimConfig, ['robot{i}/pose', 'ground_truth_landmarks']),
}
TIMEOUT_S = 30.0


def run(name, *args):
    """Run a console script of the package to its end; return the CompletedProcess."""
    script = BIN / name
    if not script.is_file():
        pytest.skip(f'{script} is not installed (pip install -e .)')
    env = dict(os.environ, ROS_DOMAIN_ID=str(next_domain_id()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([str(script), *args], env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)


@pytest.mark.parametrize('flag', ['--help', '-h'])
@pytest.mark.parametrize('name', list(SCRIPTS))
def test_help_prints_usage_and_exits_0(name, flag):
    config_class, topics = SCRIPTS[name]
    result = run(name, flag, '--ros-args', '-r', '__ns:=/robot1')
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f'usage: {name} ')
    assert f"'/**/{name}'" in result.stdout and '--params-file' in result.stdout
    for topic in topics:
        assert topic in result.stdout, topic
    for spec in fields(config_class):
        assert f'\n  {spec.name} (' in result.stdout, spec.name
    assert 'Traceback' not in result.stderr


@pytest.mark.parametrize('name', list(SCRIPTS))
def test_missing_params_file_is_one_line_and_exit_2(name, tmp_path):
    missing = tmp_path / 'nowhere.yaml'
    result = run(name, '--ros-args', '--params-file', str(missing))
    assert result.returncode == 2
    assert result.stderr == f'{name}: parameter file not found: {missing}\n'


@pytest.mark.parametrize('args, message', [
    (['--ros-args', '-r', 'bad'], "bad command line: Couldn't parse remap rule: '-r bad'"),
    (['--ros-args', '-p', 'sensor_pose:=[0.0, 0, 1]'], 'write doubles with a decimal point'),
    (['--verbose'], "unknown argument '--verbose'"),
])
def test_bad_command_line_is_one_line_and_exit_2(args, message):
    result = run('landmark_observer', *args)
    assert result.returncode == 2
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith('landmark_observer: '), result.stderr
    assert message in lines[0]
    assert ', at /' not in lines[0]


def test_a_bad_params_file_is_one_line_and_exit_2(tmp_path):
    path = tmp_path / 'broken.yaml'
    path.write_text('/**/landmark_fuser:\n  ros__parameters:\n    fusion: [a, 1.0\n')
    result = run('landmark_fuser', '--ros-args', '--params-file', str(path))
    assert result.returncode == 2
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith("landmark_fuser: bad command line: Couldn't parse params")


def test_empty_input_topics_gives_the_packages_message():
    result = run('landmark_fuser', '--ros-args', '-p', 'input_topics:=[]')
    assert result.returncode == 2
    assert result.stderr == ('landmark_fuser: invalid parameters: input_topics must list at '
                             'least one topic name\n')


def test_a_string_for_a_double_says_what_to_write():
    result = run('landmark_observer', '--ros-args', '-p', 'range_stddev:=wide')
    assert result.returncode == 2
    assert result.stderr == ('landmark_observer: invalid parameters: range_stddev is of type '
                             "double, got the string 'wide': write e.g. range_stddev:=0.1\n")


def test_a_stop_signal_before_rclpy_handles_signals_ends_the_run(monkeypatch):
    # The runner's SIGINT handler does not raise (rclpy's, installed by init, stops
    # the node); a SIGINT that comes before rclpy's handler is there still ends the
    # run, with exit code 0 and no node built.
    import signal
    from landmark_ros.ros import runner
    built, shut = [], []

    def init(argv, name):
        os.kill(os.getpid(), signal.SIGINT)      # the handler runs before this returns
        return None
    monkeypatch.setattr(runner, '_init', init)
    monkeypatch.setattr(runner.rclpy, 'try_shutdown', lambda *args: shut.append(1))
    previous = signal.getsignal(signal.SIGINT)
    try:
        assert runner.run(lambda: built.append(1), 'landmark_fuser', ['landmark_fuser']) == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    assert built == [] and shut == [1]
