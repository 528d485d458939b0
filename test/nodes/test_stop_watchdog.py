"""A node whose stop hangs ends anyway, with its stacks on stderr (``nodes.start``)."""

import os
import subprocess
import sys
import time

from rosutil import next_domain_id

SCRIPT = """
import sys, threading
from landmark_ros.nodes import start
start.EXIT_DEADLINE_S = {deadline}
code = start.finish(0)
if {hang}:
    threading.Event().wait()     # an exit that never ends (a stuck DDS teardown, say)
sys.exit(code)
"""


def _run(hang, deadline=0.5):
    begin = time.monotonic()
    proc = subprocess.run([sys.executable, '-c', SCRIPT.format(deadline=deadline, hang=hang)],
                          capture_output=True, text=True, timeout=60)
    return proc, time.monotonic() - begin


def test_a_hung_exit_dumps_the_stacks_and_ends_with_code_1():
    proc, elapsed = _run(hang=True)
    assert proc.returncode == 1, proc.stderr
    assert elapsed < 30.0
    assert 'most recent call first' in proc.stderr
    assert '<string>", line 7' in proc.stderr     # where it hung


def test_a_clean_exit_is_not_touched():
    proc, _ = _run(hang=False, deadline=30.0)
    assert proc.returncode == 0 and proc.stderr == ''


def test_the_runner_disarms_the_watchdog_when_the_teardown_is_done():
    # runner.run arms it for the teardown and disarms it: an in-process caller lives on.
    script = (
        'import threading\n'
        'from landmark_ros.ros import runner\n'
        'runner.STOP_DEADLINE_S = 0.3\n'
        'class Fails:\n'
        '    def __init__(self):\n'
        '        raise ValueError("bad value")\n'
        'print(runner.run(Fails, "landmark_fuser", ["landmark_fuser"]))\n'
        'threading.Event().wait(5 * runner.STOP_DEADLINE_S)\n'    # 5 deadlines: no exit
        'print("alive")\n')
    proc = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          timeout=120, env=_ros_env())
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ['2', 'alive']


def _ros_env():
    return dict(os.environ, ROS_DOMAIN_ID=str(next_domain_id()),
                ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
