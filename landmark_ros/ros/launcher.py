"""
A small process launcher for demos and tests (the ROS ``launch`` package is not on PyPI).

Starts named processes (usually ``python -m <module> --ros-args ...``) with a common
environment: a ROS_DOMAIN_ID, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (DDS stays
on the loopback interface), ROS file logs in the log directory; each process's
output goes to ``<log_dir>/<name>.log``. It notices processes that exit on their
own and stops all of them cleanly: SIGINT (rclpy shuts down and removes its DDS
resources), then SIGTERM and SIGKILL after deadlines. Used as a context manager
nothing is left running, whatever happens in the ``with`` block, Ctrl-C included.

Fast DDS keeps shared-memory files in ``/dev/shm`` (``fastrtps_*``, ``sem.fastrtps_*``,
``fast_datasharing_*``) and removes them on a clean shutdown. The launcher notes which
of them each process maps; files of processes that had to be killed are removed
when no living process maps them any more.
"""

import ctypes
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

SHM_DIR = '/dev/shm'
SHM_PREFIXES = ('fastrtps_', 'sem.fastrtps_', 'fast_datasharing_')
"""Shared-memory files of Fast DDS (segments, port files, their semaphores)."""
LOCALHOST_ENV = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}

try:  # Linux: a child gets a signal when the launcher dies, even by SIGKILL.
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
    _PR_SET_PDEATHSIG = 1
except (AttributeError, OSError):  # pragma: no cover - not Linux
    _PRCTL = None


class ProcessExitedError(RuntimeError):
    """A launched process exited while it should have been running."""

    def __init__(self, process):
        self.process = process
        super().__init__(
            f'{process.name} (pid {process.pid}) exited with code {process.returncode}; '
            f'its log {process.log_path} ends with:\n{process.tail()}')


def ros_module_command(module, ros_args=(), args=()):
    """
    Return the command line that runs a Python module as a ROS node.

    Parameters
    ----------
    module : str
        Module with a ``__main__`` guard, e.g. ``landmark_ros.nodes.fuser``.
    ros_args : sequence of str
        Arguments after ``--ros-args`` (``-p``, ``-r``, ``--params-file`` ...).
    args : sequence of str
        Arguments before ``--ros-args``.

    Returns
    -------
    list of str

    """
    command = [sys.executable, '-m', module, *args]
    if ros_args:
        command += ['--ros-args', *ros_args]
    return command


def write_params_file(path, parameters):
    """
    Write a ROS parameter file.

    Parameters
    ----------
    path : str or Path
        File to write.
    parameters : dict
        ``node name or pattern -> {parameter: value}``, e.g.
        ``{'/**/landmark_observer': {'range_stddev': 0.1}}``; tuples become lists.

    """
    import yaml

    def plain(value):
        return list(value) if isinstance(value, tuple) else value

    document = {node: {'ros__parameters': {k: plain(v) for k, v in values.items()}}
                for node, values in parameters.items()}
    Path(path).write_text(yaml.safe_dump(document, sort_keys=False))


def shm_files_of(pid):
    """
    Return the Fast DDS shared-memory files a process maps (empty if it is gone).

    Parameters
    ----------
    pid : int
        Process ID.

    Returns
    -------
    set of str
        Absolute paths under ``/dev/shm``.

    """
    found = set()
    try:
        with open(f'/proc/{pid}/maps') as maps:
            for line in maps:
                parts = line.split(None, 5)
                path = parts[5].strip() if len(parts) == 6 else ''
                if (path.startswith(SHM_DIR + '/') and not path.endswith('(deleted)')
                        and os.path.basename(path).startswith(SHM_PREFIXES)):
                    found.add(path)
    except OSError:  # gone, or not ours to read
        pass
    return found


def mapped_by_anyone(paths):
    """Return which of ``paths`` some living process maps."""
    paths = set(paths)
    used = set()
    if not paths:
        return used
    for entry in os.listdir('/proc'):
        if entry.isdigit():
            used |= shm_files_of(int(entry)) & paths
            if used == paths:
                break
    return used


def companions(path):
    """
    Return a Fast DDS shared-memory file with the files that belong to it.

    A segment ``fastrtps_<id>`` has a lock file ``fastrtps_<id>_el``; a port file
    ``fastrtps_port<n>`` also has a semaphore ``sem.fastrtps_port<n>_mutex``.
    """
    directory, name = os.path.split(path)
    if name.startswith('sem.'):
        return [path]
    result = [path, os.path.join(directory, name + '_el')]
    if name.startswith('fastrtps_port'):
        result.append(os.path.join(directory, f'sem.{name}_mutex'))
    return result


def semaphore_port(path):
    """Return the port file a ``sem.fastrtps_port<n>_mutex`` belongs to, else None."""
    directory, name = os.path.split(path)
    match = re.fullmatch(r'sem\.(fastrtps_port\d+)_mutex', name)
    return os.path.join(directory, match.group(1)) if match else None


def orphan_semaphores(paths):
    """
    Return the port semaphores of ``paths`` whose port file is gone.

    A port file ``fastrtps_port<n>`` in ``paths`` (existing or not) stands for its
    semaphore ``sem.fastrtps_port<n>_mutex``; a semaphore in ``paths`` for itself. The
    last user of a port may remove the port file and leave its semaphore.
    """
    found = set()
    for path in paths:
        directory, name = os.path.split(path)
        if re.fullmatch(r'fastrtps_port\d+', name):
            found.add(os.path.join(directory, f'sem.{name}_mutex'))
        elif semaphore_port(path):
            found.add(path)
    return {sem for sem in found
            if os.path.exists(sem) and not os.path.exists(semaphore_port(sem))}


def remove_unused_shm(paths):
    """
    Remove the Fast DDS shared-memory files of ``paths`` that no living process maps.

    Segments and port files are candidates; their lock files and semaphores go with
    them. A file in use is mapped by its users, so an unmapped one is left over; so is
    the semaphore of a port whose file is gone (``orphan_semaphores``).

    Parameters
    ----------
    paths : iterable of str
        Files some processes mapped (from ``shm_files_of``).

    Returns
    -------
    list of str
        Files removed.

    """
    paths = set(paths)
    candidates = {p for p in paths if os.path.exists(p)
                  and not os.path.basename(p).startswith('sem.')} | orphan_semaphores(paths)
    removed = []
    for path in sorted(candidates - mapped_by_anyone(candidates)):
        for file in companions(path):
            try:
                os.unlink(file)
                removed.append(file)
            except OSError:  # already gone, or not ours to remove
                pass
    return removed


def _prepare_child():  # runs in the child between fork and exec
    # A launcher started in the background of a script inherits an ignored SIGINT,
    # which exec would pass on: the children must stop on the SIGINT they are sent.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    if _PRCTL is not None:
        _PRCTL(_PR_SET_PDEATHSIG, signal.SIGINT)


class ManagedProcess:
    """One launched process, its log and the shared-memory files it was seen to map."""

    def __init__(self, name, command, log_path, popen):
        self.name = name
        self.command = command
        self.log_path = log_path
        self.popen = popen
        self.shm_files = set()
        self.stopping = False
        self.signals = []
        """Signals the launcher sent, in order (names)."""

    @property
    def pid(self):
        """Process ID."""
        return self.popen.pid

    @property
    def returncode(self):
        """Exit code (negative: killed by that signal), None while running."""
        return self.popen.poll()

    @property
    def running(self):
        """Whether the process is still alive."""
        return self.popen.poll() is None

    @property
    def clean_exit(self):
        """Whether it exited by itself or on SIGINT alone, with code 0."""
        return self.returncode == 0 and self.signals in ([], ['SIGINT'])

    def record_shm(self):
        """Add the shared-memory files the process maps now."""
        if self.running:
            self.shm_files |= shm_files_of(self.pid)

    def signal(self, signum):
        """Send a signal if the process still runs."""
        if self.running:
            try:
                self.popen.send_signal(signum)
                self.signals.append(signal.Signals(signum).name)
            except ProcessLookupError:
                pass

    def tail(self, lines=15):
        """Return the last lines of the log."""
        try:
            text = Path(self.log_path).read_text(errors='replace')
        except OSError as error:
            return f'(cannot read the log: {error})'
        return '\n'.join(text.rstrip().splitlines()[-lines:]) or '(empty log)'


class Launcher:
    """
    Start named processes in one ROS domain and stop them all, whatever happens.

    Parameters
    ----------
    log_dir : str or Path
        Where each process's output goes (``<name>.log``), and ROS file logs
        (``ros/``); created if needed.
    domain_id : int, optional
        ROS_DOMAIN_ID of every process; the caller's environment's by default.
    env : dict, optional
        More environment variables for every process.
    sigint_timeout_s : float
        How long processes get to exit after SIGINT before SIGTERM.
    sigterm_timeout_s : float
        How long after SIGTERM before SIGKILL.
    shm_period_s : float
        How often ``check`` looks up the shared-memory files of the processes.

    """

    def __init__(self, log_dir, domain_id=None, env=None, sigint_timeout_s=8.0,
                 sigterm_timeout_s=3.0, shm_period_s=1.0):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ)
        self.env.update(env or {})
        self.env.update(LOCALHOST_ENV)
        if domain_id is not None:
            self.env['ROS_DOMAIN_ID'] = str(int(domain_id))
        self.env.setdefault('ROS_LOG_DIR', str(self.log_dir / 'ros'))
        self.env['PYTHONUNBUFFERED'] = '1'
        self.env.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
        self.sigint_timeout_s = sigint_timeout_s
        self.sigterm_timeout_s = sigterm_timeout_s
        self.shm_period_s = shm_period_s
        self._shm_checked = -float('inf')
        self.processes = {}
        self.removed_shm = []
        """Leftover shared-memory files of killed processes the launcher removed."""
        self.shm_in_use = set()
        """Files of dead processes that another process still mapped at the cleanup
        (``remove_shm_in_use`` retries them)."""

    # Starting ---------------------------------------------------------------------

    def start(self, name, command):
        """
        Start a process; its output goes to ``<log_dir>/<name>.log``.

        Parameters
        ----------
        name : str
            Unique name (also of the log file).
        command : list of str
            Command line, e.g. from ``ros_module_command``.

        Returns
        -------
        ManagedProcess

        Raises
        ------
        ValueError
            If the name is already used.
        OSError
            If the process cannot be started.

        """
        if name in self.processes:
            raise ValueError(f'a process named {name!r} was already started')
        log_path = self.log_dir / f'{name}.log'
        with open(log_path, 'wb') as log:
            log.write(f'$ {" ".join(command)}\n'.encode())
            log.flush()
            popen = subprocess.Popen(
                command, env=self.env, stdin=subprocess.DEVNULL, stdout=log,
                stderr=subprocess.STDOUT,
                # Own process group: a Ctrl-C in the terminal reaches only the
                # launcher, which stops the processes in order.
                start_new_session=True,
                preexec_fn=_prepare_child)
        process = ManagedProcess(name, command, str(log_path), popen)
        self.processes[name] = process
        return process

    def start_module(self, name, module, ros_args=(), args=()):
        """Start ``python -m module [args] --ros-args ros_args``; see ``start``."""
        return self.start(name, ros_module_command(module, ros_args, args))

    # Watching -----------------------------------------------------------------------

    def exited(self):
        """Return the processes that exited although nobody stopped them."""
        return [p for p in self.processes.values() if not p.stopping and not p.running]

    def check(self):
        """
        Raise if a process exited on its own; note the shared memory of the others.

        The shared-memory files are looked up at most every ``shm_period_s``.

        Raises
        ------
        ProcessExitedError
            For the first process that exited.

        """
        now = time.monotonic()
        if now - self._shm_checked >= self.shm_period_s:
            self._shm_checked = now
            for process in self.processes.values():
                process.record_shm()
        gone = self.exited()
        if gone:
            raise ProcessExitedError(gone[0])

    # Stopping -----------------------------------------------------------------------

    def _wait(self, processes, timeout_s):
        deadline = time.monotonic() + timeout_s
        for process in processes:
            remaining = deadline - time.monotonic()
            try:
                process.popen.wait(timeout=max(remaining, 0.0))
            except subprocess.TimeoutExpired:
                pass
        return [p for p in processes if p.running]

    def stop(self, names=None):
        """
        Stop processes: SIGINT, then SIGTERM, then SIGKILL, each after its deadline.

        Parameters
        ----------
        names : iterable of str, optional
            Which; all by default.

        Returns
        -------
        dict
            ``name -> exit code`` of the processes stopped.

        """
        chosen = [self.processes[n] for n in names] if names is not None else list(
            self.processes.values())
        for process in chosen:
            process.record_shm()
            process.stopping = True
        try:
            running = [p for p in chosen if p.running]
            for process in running:
                process.signal(signal.SIGINT)
            running = self._wait(running, self.sigint_timeout_s)
            for process in running:
                process.signal(signal.SIGTERM)
            running = self._wait(running, self.sigterm_timeout_s)
        except KeyboardInterrupt:
            # A second Ctrl-C: do not wait any longer, but leave nothing behind.
            self._kill([p for p in chosen if p.running])
            self.cleanup_shm(chosen)
            raise
        self._kill(running)
        self.cleanup_shm(chosen)
        return {p.name: p.returncode for p in chosen}

    def _kill(self, processes):
        for process in processes:
            process.signal(signal.SIGKILL)
        for process in processes:
            process.popen.wait()

    def cleanup_shm(self, processes):
        """
        Remove the shared-memory files of dead processes that nobody maps any more.

        Clean exits remove their own files; this catches those of killed processes.

        Returns
        -------
        list of str
            Files removed.

        """
        candidates = set()
        for process in processes:
            if not process.running:
                candidates |= process.shm_files
        removed = remove_unused_shm(candidates)
        self.removed_shm += removed
        self.shm_in_use |= {p for p in candidates if os.path.exists(p)} - set(removed)
        return removed

    def remove_shm_in_use(self):
        """
        Remove the files ``cleanup_shm`` left because another process still mapped them.

        A killed node's segment stays mapped by the processes that wrote to it (the
        caller's own node, say) until they let it go: call this after they did.

        Returns
        -------
        list of str
            Files removed.

        """
        removed = remove_unused_shm(self.shm_in_use)
        self.shm_in_use = {p for p in self.shm_in_use if os.path.exists(p)}
        self.removed_shm += removed
        return removed

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.stop()
        return False
