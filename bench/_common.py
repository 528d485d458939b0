"""
Pieces shared by the benchmarks in ``bench/``.

The benchmarks run as scripts (``python bench/bench_x.py``), so this module is
imported as ``_common`` from the script's directory; processes spawned by
``multiprocessing`` inherit that ``sys.path`` and import it the same way.

Importing it sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (DDS discovery stays
on this machine). It imports nothing outside the standard library at module level:
``summary.py`` uses it without ROS or numpy, ``bench_core.py`` without ROS; the
ROS pieces import rclpy when called.

Contents: the machine description every benchmark and the summary print (``machine``,
``machine_line``, ``cpu_model``, ``git_commit``), report and timing helpers
(``verdict``, ``median_of``, ``time_per_call``, ``profile_calls``, ``profile_where``,
``package_of``),
process measurements (``process_cpu_s``, ``vm_hwm_kb``), the node-process plumbing
(``relay``, ``Server``, ``shutdown``) and the driver's pieces (``header``,
``wait_for_match``, ``take``, ``Target``).
"""

import math
import os
import platform
import statistics
import subprocess
import sys
import time

# DDS discovery stays on this machine; set before rclpy is imported.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


# --- Machine and report. --------------------------------------------------------------

def cpu_model():
    """Return the CPU model name from ``/proc/cpuinfo``, else the platform's processor."""
    cpu = platform.processor() or platform.machine()
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as cpuinfo:
            for line in cpuinfo:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    return cpu


def machine():
    """
    Describe the machine and the code: the one description every benchmark prints.

    Returns
    -------
    dict
        ``cpu`` (model name), ``cpu_count``, ``usable_cpus`` (this process's affinity),
        ``platform``, ``python``, ``numpy`` ('?' without numpy), ``rmw`` (the loaded
        rclpy's middleware, else ``RMW_IMPLEMENTATION``, else '?'), ``load`` (1-minute
        load average) and ``commit`` (short hash, '+ uncommitted changes' when the
        tracked files differ from it; '?' outside git).

    """
    try:
        import numpy
        numpy_version = numpy.__version__
    except ImportError:
        numpy_version = '?'
    rmw = os.environ.get('RMW_IMPLEMENTATION', '?')
    if 'rclpy' in sys.modules:  # never import ROS just to describe the machine
        try:
            from rclpy.utilities import get_rmw_implementation_identifier
            rmw = get_rmw_implementation_identifier()
        except (ImportError, RuntimeError):
            pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else None
    return {'cpu': cpu_model(), 'cpu_count': os.cpu_count(), 'usable_cpus': usable,
            'platform': f'{platform.system()} {platform.machine()}',
            'python': platform.python_version(), 'numpy': numpy_version, 'rmw': rmw,
            'load': os.getloadavg()[0] if hasattr(os, 'getloadavg') else float('nan'),
            'commit': git_commit()}


def git_commit():
    """Return the short commit of this checkout, marked when tracked files changed."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=here,
                                capture_output=True, text=True, check=True,
                                timeout=10).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no'],
                               cwd=here, capture_output=True, text=True, check=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return '?'
    return commit + (' + uncommitted changes' if dirty else '')


def machine_line(host, domain_id=None, load_end=None):
    """Return the report's machine line for ``machine()``, the ROS domain and the load."""
    domain = '' if domain_id is None else f'; domain {domain_id}'
    end = '' if load_end is None else f', {load_end:.1f} at end'
    return (f'machine: {host["cpu"]}; {host["cpu_count"]} CPUs ({host["usable_cpus"]} '
            f'usable); {host["platform"]}; Python {host["python"]}; numpy {host["numpy"]}; '
            f'{host["rmw"]}{domain}; commit {host["commit"]}; load average '
            f'{host["load"]:.1f} at start{end}')


def verdict(ok):
    """Return ``'PASS'`` or ``'FAIL'``."""
    return 'PASS' if ok else 'FAIL'


def median_of(runs, key, skip_nan=False):
    """Return the median of ``run[key]`` over the runs (NaN if none), NaNs left out if asked."""
    values = [run[key] for run in runs]
    if skip_nan:
        values = [value for value in values if not math.isnan(value)]
    return statistics.median(values) if values else float('nan')


def profile_where(key):
    """Return a short ``file:line(function)`` for a ``pstats`` key."""
    filename, line, function = key
    if filename == '~':
        return function
    for marker in ('/site-packages/', '/landmark_ros/'):
        if marker in filename:
            filename = filename.split(marker, 1)[1]
            break
    return f'{filename}:{line}({function})'


def package_of(key):
    """Return the package a ``pstats`` key's code belongs to (numpy's C calls apart)."""
    filename, _, function = key
    if filename == '~':
        for package in ('rclpy', 'numpy'):
            if package in function:
                return f'{package} (C)'
        return 'builtins'
    if '/landmark_ros/' in filename:
        return 'landmark_ros.' + filename.rsplit('/landmark_ros/', 1)[1][:-3].replace('/', '.')
    if '/site-packages/' in filename:
        return filename.split('/site-packages/', 1)[1].split('/', 1)[0]
    return os.path.basename(filename)


def profile_calls(function, calls, top):
    """
    Run ``function(i)`` for ``i`` in ``range(calls)`` under cProfile.

    Returns
    -------
    functions : list of (where, tottime_us, cumtime_us, calls)
        The ``top`` functions by own time, per call of ``function``.
    packages : list of (package, tottime_us)
        Own time per call of ``function`` by package, largest first.
    total_us : float
        Own time per call of ``function`` under the profiler.
    calls_per_call : float
        Function calls the profiler saw per call of ``function``.

    """
    import cProfile
    import pstats
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(calls):
        function(i)
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    entries = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)
    functions = [(profile_where(key), tt / calls * 1e6, ct / calls * 1e6, nc / calls)
                 for key, (_, nc, tt, ct, _) in entries[:top]]
    packages = {}
    for key, (_, _, tt, _, _) in stats.items():
        packages[package_of(key)] = packages.get(package_of(key), 0.0) + tt / calls * 1e6
    total = sum(packages.values())
    return (functions, sorted(packages.items(), key=lambda item: -item[1]), total,
            sum(nc for _, nc, _, _, _ in stats.values()) / calls)


def time_per_call(function, calls, blocks, warmup=16):
    """
    Time ``function(i)`` over ``calls`` calls split into ``blocks``, garbage collector off.

    Returns
    -------
    wall : list of float
        Wall seconds per call of each block.
    cpu : list of float
        CPU seconds of this thread per call of each block: what waiting for a core
        (other load on the machine) does not inflate.

    """
    import gc
    for i in range(warmup):
        function(i)
    per_block = max(1, calls // blocks)
    wall, cpu = [], []
    enabled = gc.isenabled()
    gc.disable()
    try:
        i = warmup
        for _ in range(blocks):
            start, cpu_start = time.perf_counter(), time.thread_time()
            for _ in range(per_block):
                function(i)
                i += 1
            cpu.append((time.thread_time() - cpu_start) / per_block)
            wall.append((time.perf_counter() - start) / per_block)
    finally:
        if enabled:
            gc.enable()
    return wall, cpu


# --- Process measurements. ----------------------------------------------------------

def process_cpu_s(pid):
    """Return user + system CPU seconds of a process (all its threads), or NaN."""
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii') as stat:
            fields = stat.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return float('nan')


def vm_hwm_kb():
    """Return this process's peak RSS (``VmHWM``) [kB], or None."""
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


# --- Nodes under test, each in its own process. ---------------------------------------

def relay(input_topic, input_qos, output_topic, output_qos, **kwargs):
    """
    Return a node that republishes every PointCloud2 unchanged: the executor-only baseline.

    The node is named ``bench_relay``; it has ``subscription`` (on ``input_topic``),
    ``publisher`` (on ``output_topic``) and ``count`` (the messages relayed).
    ``kwargs`` go to ``rclpy.node.Node`` (context, namespace).
    """
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    class Relay(Node):
        """Republish every cloud unchanged."""

        def __init__(self):
            super().__init__('bench_relay', **kwargs)
            self.count = 0
            self.publisher = self.create_publisher(PointCloud2, output_topic, output_qos)
            self.subscription = self.create_subscription(PointCloud2, input_topic,
                                                         self.on_message, input_qos)

        def on_message(self, msg):
            """Publish the message as it came."""
            self.count += 1
            self.publisher.publish(msg)

    return Relay()


def shutdown(executor, node, context, conn):
    """Shut down a node process's executor, node, context and pipe end (in order)."""
    import rclpy
    if executor is not None:
        executor.shutdown()
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown(context=context)
    conn.close()


class Server:
    """
    A node under test in a spawned process, with its pipe.

    ``target(*args, conn)`` runs in the process: it sends ``('ready', pid)`` once
    spinning, ``('done', stats)`` when stopped, ``('error', text)`` on failure.
    Subclasses say how the node is told to stop (``request_stop``).
    """

    def __init__(self, mp_context, kind, target, args, duplex=True):
        self.kind = kind
        self.conn, child = mp_context.Pipe(duplex=duplex)
        self.process = mp_context.Process(target=target, name=f'bench_{kind}',
                                          args=(*args, child))
        self.process.start()
        child.close()
        self.pid = None
        self.stats = None

    def wait_ready(self, timeout):
        """Wait for the node to spin; raise RuntimeError if it does not."""
        if not self.conn.poll(timeout):
            raise RuntimeError(f'{self.kind} node not ready after {timeout} s')
        tag, value = self.conn.recv()
        if tag != 'ready':
            raise RuntimeError(f'{self.kind} node failed:\n{value}')
        self.pid = value

    def request_stop(self):
        """Tell the node to stop; return whether to wait for its final statistics."""
        raise NotImplementedError

    def stop(self, timeout=10.0):
        """Stop the node, keep its final statistics and join the process."""
        try:
            if self.request_stop() and self.conn.poll(timeout):
                tag, value = self.conn.recv()
                if tag == 'done':
                    self.stats = value
                else:
                    print(f'{self.kind} node error:\n{value}', file=sys.stderr)
        except (EOFError, OSError):
            pass
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout)
        self.conn.close()


# --- The driver: no executor, an rcl wait set and serialized messages. ---------------

def wait_for_match(pairs, timeout):
    """Wait until every (publisher, subscription) pair has found its peer."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(pub.get_subscription_count() > 0 and sub.get_publisher_count() > 0
               for pub, sub in pairs):
            return True
        time.sleep(0.02)
    return False


def wait_set_for(node):
    """Return an rcl wait set for one subscription of ``node``."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    return _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)


def take(wait_set, subscription, msg_type, raw, timeout_s):
    """Wait up to ``timeout_s`` on one subscription; return the messages it holds."""
    wait_set.clear_entities()
    wait_set.add_subscription(subscription.handle)
    wait_set.wait(int(timeout_s * 1e9))
    messages = []
    with subscription.handle:
        while True:
            taken = subscription.handle.take_message(msg_type, raw)
            if taken is None:
                return messages
            messages.append(taken[0])


class Target:
    """The driver's publisher and raw PointCloud2 output subscription for one node."""

    def __init__(self, node, kind, publisher, subscription):
        from sensor_msgs.msg import PointCloud2
        self.kind = kind
        self.publisher = publisher
        self.subscription = subscription
        self.wait_set = wait_set_for(node)
        self.msg_type = PointCloud2

    def wait(self, timeout_s):
        """Wait for outputs; return how many were taken and the last one (bytes)."""
        taken = take(self.wait_set, self.subscription, self.msg_type, True, timeout_s)
        return len(taken), (taken[-1] if taken else None)
