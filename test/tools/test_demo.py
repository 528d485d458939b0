"""
Tests of the process launcher and of the demo run end to end.

The launcher tests use plain Python child processes (no ROS) to check the
environment, the logs, the detection of unexpected exits and the SIGINT ->
SIGTERM -> SIGKILL escalation. The demo tests run ``python -m landmark_ros.demo``
in a subprocess with a deadline and check its output, its plot, and that neither
its processes nor their Fast DDS shared-memory files outlive it.
"""

import mmap
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

from landmark_ros.ros.launcher import (Launcher, ManagedProcess, mapped_by_anyone,
                                       orphan_semaphores, ProcessExitedError,
                                       remove_unused_shm, ros_module_command,
                                       semaphore_port, SHM_DIR, shm_files_of,
                                       write_params_file)
import numpy as np
import pytest
import yaml

DEADLINE_S = 20.0
"""Generous deadline for a child process to do something."""
DEMO_DEADLINE_S = 150.0
"""Deadline of a whole short demo run (a loaded 2-core machine included)."""

CHILD = r"""
import os, signal, sys
mode = sys.argv[1]
if mode in ('ignore_int', 'ignore_all'):
    signal.signal(signal.SIGINT, signal.SIG_IGN)
if mode == 'ignore_all':
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
print('domain', os.environ.get('ROS_DOMAIN_ID'))
print('range', os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'))
print('ready', flush=True)
if mode == 'exit3':
    sys.exit(3)
try:
    while True:
        signal.pause()
except KeyboardInterrupt:
    print('stopping on SIGINT', flush=True)
"""


def child(mode):
    """Return the command line of a test child process."""
    return [sys.executable, '-c', CHILD, mode]


def wait_for(predicate, process, timeout=DEADLINE_S):
    """Wait until ``predicate()`` or the deadline, blocking on ``process`` meanwhile."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return predicate()
        try:
            process.popen.wait(timeout=0.02)  # returns at once when it exits
        except subprocess.TimeoutExpired:
            pass
    return True


def ready(process):
    """Whether a child printed 'ready'."""
    return '\nready\n' in Path(process.log_path).read_text()  # not the command line


# Launcher ---------------------------------------------------------------------------

def test_children_get_the_domain_localhost_and_a_log(tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    with Launcher(tmp_path / 'logs', domain_id=177) as launcher:
        process = launcher.start('one', child('exit3'))
        assert wait_for(lambda: not process.running, process)
        log = Path(process.log_path).read_text()
        assert process.log_path == str(tmp_path / 'logs' / 'one.log')
        assert 'domain 177' in log and 'range LOCALHOST' in log
        assert launcher.env['ROS_LOG_DIR'] == str(tmp_path / 'logs' / 'ros')
        # An exit nobody asked for is reported, with the end of the log.
        with pytest.raises(ProcessExitedError, match='one .* exited with code 3') as error:
            launcher.check()
        assert 'ready' in str(error.value)
        assert launcher.exited() == [process]


def test_stop_escalates_from_sigint_to_sigterm_to_sigkill(tmp_path):
    launcher = Launcher(tmp_path, sigint_timeout_s=1.0, sigterm_timeout_s=1.0)
    polite = launcher.start('polite', child('run'))
    stubborn = launcher.start('stubborn', child('ignore_int'))
    deaf = launcher.start('deaf', child('ignore_all'))
    assert wait_for(lambda: all(ready(p) for p in (polite, stubborn, deaf)), polite)
    launcher.check()  # all running: nothing to report
    codes = launcher.stop()
    assert codes == {'polite': 0, 'stubborn': -signal.SIGTERM, 'deaf': -signal.SIGKILL}
    assert polite.signals == ['SIGINT'] and polite.clean_exit
    assert 'stopping on SIGINT' in Path(polite.log_path).read_text()
    assert stubborn.signals == ['SIGINT', 'SIGTERM'] and not stubborn.clean_exit
    assert deaf.signals == ['SIGINT', 'SIGTERM', 'SIGKILL']
    assert not any(p.running for p in (polite, stubborn, deaf))
    assert launcher.exited() == []  # stopped on purpose: not unexpected


def test_context_manager_stops_everything_on_an_exception(tmp_path):
    with pytest.raises(RuntimeError, match='boom'):
        with Launcher(tmp_path) as launcher:
            processes = [launcher.start(f'p{i}', child('run')) for i in range(2)]
            assert wait_for(lambda: all(ready(p) for p in processes), processes[0])
            raise RuntimeError('boom')
    assert not any(p.running for p in processes)
    assert all(p.returncode == 0 for p in processes)


def test_names_are_unique(tmp_path):
    with Launcher(tmp_path) as launcher:
        launcher.start('same', child('exit3'))
        with pytest.raises(ValueError, match='same'):
            launcher.start('same', child('exit3'))


def test_module_command_and_params_file(tmp_path):
    command = ros_module_command('landmark_ros.nodes.sim', ['-p', 'robots:=2'])
    assert command == [sys.executable, '-m', 'landmark_ros.nodes.sim', '--ros-args', '-p',
                       'robots:=2']
    assert ros_module_command('x') == [sys.executable, '-m', 'x']
    path = tmp_path / 'params.yaml'
    write_params_file(path, {'/**/landmark_observer': {
        'range_stddev': 0.2, 'sensor_pose': (0.0, 0.1, 0.0)}})
    assert yaml.safe_load(path.read_text()) == {'/**/landmark_observer': {
        'ros__parameters': {'range_stddev': 0.2, 'sensor_pose': [0.0, 0.1, 0.0]}}}


def test_leftover_shared_memory_of_dead_processes_is_removed(tmp_path):
    launcher = Launcher(tmp_path)
    name = f'{SHM_DIR}/fastrtps_landmark_ros_test_{os.getpid()}'
    files = [name, name + '_el', f'{name}_inuse', f'{name}_inuse_el']
    for file in files:
        Path(file).write_bytes(b'\0' * 64)
    try:
        dead = ManagedProcess('dead', ['true'], str(tmp_path / 'dead.log'),
                              subprocess.Popen(['true']))
        dead.popen.wait()
        dead.shm_files = {name, f'{name}_inuse'}
        with open(f'{name}_inuse', 'r+b') as stream:
            mapped = mmap.mmap(stream.fileno(), 64)  # still in use by this process
            try:
                assert shm_files_of(os.getpid()) >= {f'{name}_inuse'}
                assert mapped_by_anyone({name, f'{name}_inuse'}) == {f'{name}_inuse'}
                removed = launcher.cleanup_shm([dead])
            finally:
                mapped.close()
        assert removed == [name, name + '_el']
        assert not os.path.exists(name) and not os.path.exists(name + '_el')
        assert os.path.exists(f'{name}_inuse')
        # Mapped no more (the caller's node let the dead one's segment go): retried.
        assert launcher.shm_in_use == {f'{name}_inuse'}
        assert launcher.remove_shm_in_use() == [f'{name}_inuse', f'{name}_inuse_el']
        assert not os.path.exists(f'{name}_inuse') and not launcher.shm_in_use
    finally:
        for file in files:
            if os.path.exists(file):
                os.unlink(file)


def test_the_semaphore_of_a_removed_port_is_removed_when_unused():
    number = 90000 + os.getpid() % 9000
    port = f'{SHM_DIR}/fastrtps_port{number}'
    semaphore = f'{SHM_DIR}/sem.fastrtps_port{number}_mutex'
    Path(semaphore).write_bytes(b'\0' * 32)
    try:
        Path(port).write_bytes(b'\0' * 32)
        assert orphan_semaphores([port]) == set()     # its port is still there
        os.unlink(port)
        assert orphan_semaphores([port]) == orphan_semaphores([semaphore]) == {semaphore}
        with open(semaphore, 'r+b') as stream:
            mapped = mmap.mmap(stream.fileno(), 32)     # in use: kept
            try:
                assert remove_unused_shm([port]) == []
            finally:
                mapped.close()
        assert remove_unused_shm([port]) == [semaphore]
        assert not os.path.exists(semaphore)
    finally:
        for file in (port, semaphore):
            if os.path.exists(file):
                os.unlink(file)


def test_a_port_semaphore_is_left_over_only_when_its_port_is_unused():
    # Fast DDS maps a port's semaphore only while it holds it: a semaphore the demo was
    # seen to map belongs to whoever still maps the port file, in any domain.
    port = f'{SHM_DIR}/fastrtps_port{90000 + os.getpid() % 9000}'
    semaphore = f'{SHM_DIR}/sem.{os.path.basename(port)}_mutex'
    assert semaphore_port(semaphore) == port and semaphore_port(port) is None
    for file in (port, semaphore):
        Path(file).write_bytes(b'\0' * 64)
    try:
        with open(port, 'r+b') as stream:
            mapped = mmap.mmap(stream.fileno(), 64)  # another user of the port
            try:
                assert_nothing_left({}, {semaphore}, 0, set())
            finally:
                mapped.close()
        with pytest.raises(AssertionError, match='left behind'):
            assert_nothing_left({}, {semaphore}, 0, set())
    finally:
        for file in (port, semaphore):
            if os.path.exists(file):
                os.unlink(file)


# The demo ---------------------------------------------------------------------------

def descendants(pid):
    """Return the PIDs of the living descendants of ``pid``."""
    found, todo = set(), [pid]
    while todo:
        parent = todo.pop()
        try:
            tasks = os.listdir(f'/proc/{parent}/task')
        except OSError:
            continue
        for task in tasks:
            try:
                children = Path(f'/proc/{parent}/task/{task}/children').read_text().split()
            except OSError:
                continue
            for child_pid in map(int, children):
                if child_pid not in found:
                    found.add(child_pid)
                    todo.append(child_pid)
    return found


def alive(pid, command_fragment):
    """Whether ``pid`` is a living (non-zombie) process whose command has the fragment."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
        command = Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode()
    except OSError:
        return False
    return 'State:\tZ' not in status and command_fragment in command


def port_files(domain_id):
    """Return the Fast DDS shared-memory port files of a domain that exist now."""
    low = 7400 + 250 * domain_id
    result = set()
    for name in os.listdir(SHM_DIR):
        match = re.fullmatch(r'fastrtps_port(\d+)', name)
        if match and low <= int(match.group(1)) < low + 250:
            result.add(f'{SHM_DIR}/{name}')
    return result


def run_demo(tmp_path, *args):
    """
    Run the demo with a deadline while noting its processes and shared memory.

    Returns
    -------
    returncode : int
    output : str
    children : dict
        ``pid -> command line`` of every process the demo started.
    shm : set of str
        Fast DDS shared-memory files the demo or its processes mapped.

    """
    log = tmp_path / 'demo_output.txt'
    command = [sys.executable, '-m', 'landmark_ros.demo', '--output',
               str(tmp_path / 'demo.png'), *args]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    children, shm = {}, set()
    with open(log, 'w') as out:
        demo = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + DEMO_DEADLINE_S
        try:
            while True:
                for pid in descendants(demo.pid):
                    try:  # read again: empty during exec, the parent's before it
                        command = Path(f'/proc/{pid}/cmdline').read_bytes()
                    except OSError:
                        continue
                    if command:
                        children[pid] = command.replace(b'\0', b' ').decode()
                    shm |= shm_files_of(pid)
                shm |= shm_files_of(demo.pid)
                try:
                    demo.wait(timeout=0.2)  # wakes up as soon as the demo exits
                    break
                except subprocess.TimeoutExpired:
                    if time.monotonic() > deadline:
                        raise
        finally:
            if demo.poll() is None:  # deadline: Ctrl-C it, which must clean up too
                demo.send_signal(signal.SIGINT)
                try:
                    demo.wait(timeout=30.0)
                except subprocess.TimeoutExpired:
                    demo.kill()
                    demo.wait()
    return demo.returncode, log.read_text(), children, shm


def assert_nothing_left(children, shm, domain_id, ports_before):
    """Assert no process the demo started lives on and no shared memory leaked."""
    still = {pid: cmd for pid, cmd in children.items() if alive(pid, cmd.split()[0])}
    assert not still, f'processes left running: {still}'
    leaked = {f for f in shm if os.path.exists(f)}
    leaked -= mapped_by_anyone(leaked)  # files other programs still use are theirs too
    # A port's semaphore is mapped only while it is taken; it belongs to its port file,
    # which other processes (any domain: ports 7000+ are shared) may still map.
    owners = {sem: semaphore_port(sem) for sem in leaked if semaphore_port(sem)}
    used_ports = mapped_by_anyone(set(owners.values()))
    leaked -= {sem for sem, port in owners.items() if port in used_ports}
    # The last user of a port may leave its semaphore: the demo removes those of the
    # ports it used, but a shared port's may be left again by another domain's process.
    low = 7400 + 250 * domain_id
    leaked -= {sem for sem, port in owners.items() if not os.path.exists(port)
               and not low <= int(re.search(r'\d+$', port).group()) < low + 250}
    assert not leaked, f'shared-memory files left behind: {sorted(leaked)}'
    new_ports = port_files(domain_id) - ports_before
    new_ports -= mapped_by_anyone(new_ports)
    assert not new_ports, f'port files of the demo domain left behind: {sorted(new_ports)}'


def domain_of(output):
    """Return the ROS_DOMAIN_ID the demo printed."""
    match = re.search(r'ROS_DOMAIN_ID (\d+)', output)
    assert match, output
    return int(match.group(1))


def test_short_demo_run_end_to_end(tmp_path):
    ports_before = set().union(*(port_files(d) for d in range(150, 200)))
    code, output, children, shm = run_demo(
        tmp_path, '--duration', '4', '--landmarks', '8', '--seed', '10')
    assert code == 0, output
    assert 'fusion independent' in output
    assert re.search(r'^\s+id\s+x \[m\]\s+y \[m\]\s+sd_x', output, re.M), output
    rows = re.findall(r'^\s+\d+\s+-?\d+\.\d{3}\s+-?\d+\.\d{3}\s', output, re.M)
    assert len(rows) >= 3, output
    assert re.search(r'RMSE \d+\.\d+ cm over \d+ landmarks; average NEES .*: consistent',
                     output), output
    assert 'OK: all' in output
    png = tmp_path / 'demo.png'
    assert f'plot: {png}' in output
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    logs = tmp_path / 'log' / 'demo'
    assert {'sim.log', 'fuser.log', 'observer_robot1.log', 'params.yaml',
            'fused_map.json'} <= {p.name for p in logs.iterdir()}
    # sim, three observers and the fuser, each its own process; all gone now.
    modules = sorted(re.search(r'-m (\S+)', cmd).group(1) for cmd in children.values())
    assert modules == ['landmark_ros.nodes.fuser'] + ['landmark_ros.nodes.observer'] * 3 + [
        'landmark_ros.nodes.sim'], children
    assert shm, 'no Fast DDS shared memory seen: the check below would prove nothing'
    assert_nothing_left(children, shm, domain_of(output), ports_before)


def test_demo_fails_cleanly_when_a_node_dies(tmp_path):
    ports_before = set().union(*(port_files(d) for d in range(150, 200)))
    code, output, children, shm = run_demo(
        tmp_path, '--duration', '4', '--world-file', str(tmp_path / 'missing.yaml'))
    assert code == 2, output
    assert re.search(r'demo failed: sim \(pid \d+\) exited with code 2', output), output
    assert 'missing.yaml' in output  # the end of the sim's log says why
    assert not (tmp_path / 'demo.png').exists()
    assert len(children) == 5, children
    assert_nothing_left(children, shm, domain_of(output), ports_before)


def test_short_demo_run_without_ids_matches_tracks_by_position(tmp_path):
    ports_before = set().union(*(port_files(d) for d in range(150, 200)))
    code, output, children, shm = run_demo(
        tmp_path, '--duration', '4', '--landmarks', '8', '--seed', '10', '--no-ids',
        '--no-plot')
    assert code == 0, output
    match = re.search(r'without IDs: (\d+) tracks confirmed, (\d+) matched to a true '
                      r'landmark \(of (\d+) measured\), 0 extra; GOSPA (\d+\.\d+) m', output)
    assert match, output
    tracks, matched, measured = (int(g) for g in match.groups()[:3])
    # Every track is a true landmark; every landmark sighted often enough is a track.
    assert tracks == matched >= measured >= 3, output
    # The matched tracks are reported under the IDs of their true landmarks (1 .. 8).
    rows = re.findall(r'^\s+(\d+)\s+-?\d+\.\d{3}\s+-?\d+\.\d{3}\s', output, re.M)
    assert sorted(int(r) for r in rows) == sorted({int(r) for r in rows})
    assert all(1 <= int(r) <= 8 for r in rows) and len(rows) == matched, output
    assert 'OK: all' in output
    assert_nothing_left(children, shm, domain_of(output), ports_before)


def test_tracks_are_matched_to_the_truth_by_position():
    from collections import namedtuple
    from landmark_ros.demo.report import match_tracks_to_truth
    Cloud = namedtuple('Cloud', 'ids m observations')
    truth = Cloud(np.array([1, 2, 3]), np.array([[0.0, 0.0], [2.0, 0.0], [9.0, 9.0]]),
                  np.array([10, 6, 0]))
    fused = Cloud(np.array([1000000000, 1000000001, 1000000002]),
                  np.array([[2.05, 0.0], [0.0, 0.1], [5.0, 5.0]]), np.array([8, 10, 3]))
    result = match_tracks_to_truth(fused, truth)
    assert result['track_to_true'] == {1000000000: 2, 1000000001: 1}
    assert result['tracks'] == 3 and result['extra_tracks'] == 1
    # min(10, 10) + min(8, 6) of 16 sightings.
    assert result['observations_matched'] == pytest.approx(16 / 16)
    assert result['gospa_m'] == pytest.approx(np.sqrt(0.05 ** 2 + 0.1 ** 2 + 1.0 ** 2 / 2))


def test_short_demo_run_with_a_mixed_team(tmp_path):
    # Robot 1 range-bearing, robot 2 range-only, robot 3 bearing-only: the partial
    # robots' views go through partial_observations to the fuser's partial observation topics.
    ports_before = set().union(*(port_files(d) for d in range(150, 200)))
    code, output, children, shm = run_demo(
        tmp_path, '--duration', '10', '--sensors', 'rb,range,bearing', '--no-plot')
    assert code == 0, output
    assert 'sensors rb,range,bearing' in output
    counts = {kind: (int(a), int(b)) for kind, a, b in re.findall(
        r'^(rb|range|bearing): (\d+) landmarks measured, (\d+) of them in the map', output,
        re.M)}
    assert set(counts) == {'rb', 'range', 'bearing'}, output
    assert counts['rb'][0] == counts['rb'][1] > 0, output
    # Views placed landmarks that no range-bearing robot saw.
    match = re.search(r'^(\d+) landmarks seen by range-only or bearing-only robots only: '
                      r'(\d+) placed', output, re.M)
    assert match and int(match.group(2)) >= 1, output
    params = yaml.safe_load((tmp_path / 'log' / 'demo' / 'params.yaml').read_text())
    fuser = params['/landmark_fuser']['ros__parameters']
    assert fuser['partial_observation_topics'] == ['/robot2/partial_observations',
                                                   '/robot3/partial_observations']
    assert re.search(r'average NEES .*: consistent', output), output
    assert_nothing_left(children, shm, domain_of(output), ports_before)


def test_sensor_kinds_on_the_command_line():
    from landmark_ros.demo.run import parse_args, partial_robots, sim_config
    args = parse_args(['--sensors', 'range,rb'])
    assert args.sensors == ('range', 'rb')
    config = sim_config(args)
    assert [config.sensor_kind(i) for i in range(3)] == ['range', 'rb', 'range']
    assert partial_robots(config) == [0, 2]
    for bad in (['--sensors', 'rb,lidar'], ['--sensors', 'range', '--no-ids']):
        with pytest.raises(SystemExit) as exit_info:
            parse_args(bad)
        assert exit_info.value.code == 2


def test_the_slam_demo_runs_the_fuser_without_change_detection(tmp_path):
    from landmark_ros.demo.run import node_parameters, parse_args, sim_config
    for argv, rate in (([], None), (['--slam'], 0.0)):
        args = parse_args(argv)
        fuser = node_parameters(sim_config(args), args.fusion, tmp_path / 'map.yaml',
                                args.slam)['/landmark_fuser']
        assert fuser.get('move_false_alarm_rate') == rate     # None: the package default
    assert args.fusion == 'split_covariance_intersection'     # --slam's default fusion


def test_the_simulator_waits_for_the_readers_each_mode_has():
    from landmark_ros.demo.localize import sim_waits
    from landmark_ros.demo.run import parse_args as parse
    assert sim_waits(parse([])) == {}
    localize = sim_waits(parse(['--localize']))
    assert localize == {'wait_for_odometry_subscribers': True,
                        'wait_for_true_pose_subscribers': True,
                        'wait_for_pose_subscribers': True}
    # --slam: the reported pose goes to sim_pose, which no node reads
    assert sim_waits(parse(['--slam']))['wait_for_pose_subscribers'] is False


def test_slam_prints_the_maps_nees_without_judging_it():
    from types import SimpleNamespace
    from landmark_ros.demo.run import failures_of
    summary = SimpleNamespace(consistent=False, anees=9.0, anees_interval=(1.2, 3.0))
    evaluation = ([object()], summary, set(), [], None)
    assert 'overconfident' in failures_of(evaluation, [])[0]
    assert failures_of(evaluation, [], judge_anees=False) == []
    assert failures_of(evaluation, [3], judge_anees=False) == [
        'landmarks measured but not fused: [3]']
