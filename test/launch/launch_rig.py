"""
Run ``ros2 launch`` on a colcon-built workspace as a ROS user would, and clean up after it.

Needs the ROS 2 command-line tools of ``../shared/ros-tools`` (``make test`` installs them
into the venv): tests skip cleanly without ``../shared`` (or the directory
``LANDMARK_ROS_SHARED`` names). Every process a test starts
carries a token in its environment, its own ``ROS_DOMAIN_ID`` and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; ``Launch.close`` kills its process group and
every process that still carries the token, whatever happened in the test.
"""

import os
from pathlib import Path
import re
import select
import shutil
import signal
import subprocess
import sys
import time
import uuid

import pytest

PACKAGE = 'landmark_ros'
REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get('LANDMARK_ROS_SHARED', REPO_ROOT.parent / 'shared'))
"""The repo's sibling ``shared`` directory (``LANDMARK_ROS_SHARED`` names another)."""
INSTALL_SCRIPT = SHARED / 'ros-tools' / 'install.sh'
BIN = Path(sys.executable).parent
TOKEN_VARIABLE = 'LANDMARK_ROS_TEST_TOKEN'
# Outputs colcon (or setup.py) could drop into the source tree.
POLLUTION = ('build', 'install', 'log', PACKAGE + '.egg-info')


def require_tools():
    """Skip unless ``../shared`` is there and its ROS 2 tools and colcon are installed."""
    if not INSTALL_SCRIPT.is_file():
        pytest.skip(f'{SHARED} is absent: no ROS 2 command-line tools to test with')
    missing = [name for name in ('ros2', 'colcon') if not (BIN / name).exists()]
    if missing:
        pytest.skip(f'{", ".join(missing)} not in {BIN}: run make test, or bash '
                    f'{INSTALL_SCRIPT} {BIN.parent}')


def build_workspace(workspace):
    """
    ``colcon build`` the package into ``workspace``; return the ``install`` directory.

    The numba kernels of the installed copy are compiled into its disk cache first, as
    ``make test`` does for the source tree: the nodes then start in seconds. Nothing is
    left in the source tree.
    """
    existed = {name for name in POLLUTION if (REPO_ROOT / name).exists()}
    env = dict(os.environ, COLCON_HOME=str(workspace / 'colcon_home'))
    command = [str(BIN / 'colcon'), '--log-base', str(workspace / 'log'), 'build',
               '--base-paths', str(REPO_ROOT), '--packages-select', PACKAGE,
               '--build-base', str(workspace / 'build'),
               '--install-base', str(workspace / 'install'),
               '--event-handlers', 'console_cohesion+', 'console_start_end-']
    proc = subprocess.run(command, cwd=workspace, env=env, capture_output=True, text=True,
                          timeout=600)
    for name in POLLUTION:
        if name not in existed and (REPO_ROOT / name).exists():
            shutil.rmtree(REPO_ROOT / name, ignore_errors=True)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    install = workspace / 'install'
    warm = ('from landmark_ros.fusion import compiled; compiled.load(); '
            'import landmark_ros; print(landmark_ros.__file__)')
    proc = subprocess.run(sourced(install, [sys.executable, '-c', warm]), cwd=workspace,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().startswith(str(install)), proc.stdout
    return install


def sourced(install, command):
    """Return ``command`` run by bash after ``source install/setup.bash``."""
    return ['bash', '-c', 'source "$0/setup.bash" && exec "$@"', str(install), *command]


def processes_with(token):
    """Return the PIDs of the processes whose environment holds ``token``."""
    needle = f'{TOKEN_VARIABLE}={token}'.encode()
    found = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            environ = (entry / 'environ').read_bytes()
        except OSError:     # gone, or not ours
            continue
        if needle in environ.split(b'\0'):
            found.append(int(entry.name))
    return found


def wait_for_any_exit(pids, timeout_s):
    """Return once one of ``pids`` has ended (or is gone) or after ``timeout_s``."""
    poller, fds = select.poll(), []
    try:
        for pid in pids:
            try:
                fds.append(os.pidfd_open(pid))
            except ProcessLookupError:      # ended already
                return
            poller.register(fds[-1], select.POLLIN)
        poller.poll(max(0.0, timeout_s) * 1000.0)
    finally:
        for fd in fds:
            os.close(fd)


def teardown_hangs(output):
    """
    Return the launched processes the node's stop watchdog ended inside DDS's teardown.

    A node whose teardown has not returned 10 s after its spin ended writes its Python
    stack and exits with code 1 (``nodes.start.stop_watchdog``, docs/nodes.md). Rarely,
    under load, Fast DDS's participant deletion inside rclpy's ``Node.destroy_node``
    never returns: a process counts here only when its stack's innermost frame is that
    call and launch reports it died with code 1. Anything else still fails a test.
    """
    hung = set()
    for match in re.finditer(r'^\[([\w.-]+)\] Timeout \(\d+:\d\d:\d\d\)!\n'
                             r'\[\1\] Thread 0x[0-9a-f]+ \(most recent call first\):\n'
                             r'\[\1\]   File "[^"\n]*/rclpy/node\.py", line \d+ in destroy_node$',
                             output, re.MULTILINE):
        name = match.group(1)
        if re.search(rf'^\[ERROR\] \[{re.escape(name)}\]: process has died \[pid \d+, '
                     r'exit code 1,', output, re.MULTILINE):
            hung.add(name)
    return hung


class Launch:
    """
    ``ros2 launch landmark_ros team.launch.py ARGS`` in its own session and domain.

    Parameters
    ----------
    install : Path
        The workspace's install directory.
    arguments : list of str
        Launch arguments (``name:=value``).
    domain_id : int
        ROS_DOMAIN_ID of every process.
    log_path : Path
        Where the launch's stdout and stderr go.

    """

    def __init__(self, install, arguments, domain_id, log_path):
        self.token = uuid.uuid4().hex
        self.domain_id = domain_id
        self.log_path = log_path
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
                   ROS_LOG_DIR=str(log_path.parent / 'ros_log'),
                   **{TOKEN_VARIABLE: self.token})
        command = sourced(install, [str(BIN / 'ros2'), 'launch', PACKAGE, 'team.launch.py',
                                    *arguments])
        with open(log_path, 'wb') as log:
            self.popen = subprocess.Popen(command, env=env, cwd=log_path.parent, stdout=log,
                                          stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                          start_new_session=True)

    def output(self):
        """Return what the launch printed so far."""
        return self.log_path.read_text(errors='replace')

    def interrupt(self):
        """Send SIGINT to the launch's process group, as Ctrl-C in its terminal does."""
        os.killpg(self.popen.pid, signal.SIGINT)

    def wait(self, timeout_s):
        """Return the launch's exit code once it ends (None if it still runs at the end)."""
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def left_running(self, grace_s=5.0):
        """
        Return the PIDs of the launch's processes still alive after up to ``grace_s``.

        Waits on the processes' exit (``pidfd_open`` and ``poll``), not by sleeping.
        """
        deadline = time.monotonic() + grace_s
        while True:
            pids = processes_with(self.token)
            left = deadline - time.monotonic()
            if not pids or left <= 0.0:
                return pids
            wait_for_any_exit(pids, left)

    def close(self):
        """Kill the process group and every process with the token, whatever runs."""
        try:
            os.killpg(self.popen.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        for pid in processes_with(self.token):
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        try:
            self.popen.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
