"""
Pieces shared by the benchmarks in ``bench/``.

The benchmarks run as scripts (``python bench/bench_x.py``), so this module is
imported as ``_common`` from the script's directory; processes spawned by
``multiprocessing`` inherit that ``sys.path`` and import it the same way.

Importing it sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (DDS discovery stays
on this machine). It imports nothing outside the standard library at module level:
``summary.py`` uses it without ROS or numpy, ``bench_core.py`` without ROS; the
ROS pieces import rclpy when called.

Contents: machine description and report helpers (``cpu_model``, ``machine``,
``machine_line``, ``verdict``, ``median_of``, ``profile_where``),
process measurements (``process_cpu_s``, ``vm_hwm_kb``), the node-process plumbing
(``relay``, ``Server``, ``shutdown``) and the driver's pieces (``header``,
``wait_for_match``, ``take``, ``Target``).
"""

import math
import os
import platform
import statistics
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
    """Describe the machine: CPU model, CPU count, platform, Python, numpy, rmw."""
    import numpy as np
    try:
        from rclpy.utilities import get_rmw_implementation_identifier
        rmw = get_rmw_implementation_identifier()
    except (ImportError, RuntimeError):
        rmw = os.environ.get('RMW_IMPLEMENTATION', '?')
    return {'cpu': cpu_model(), 'cpu_count': os.cpu_count(),
            'python': platform.python_version(), 'numpy': np.__version__, 'rmw': rmw}


def machine_line(host, domain_id, load_start, load_end):
    """Return the report's machine line for ``machine()``, the domain and the load."""
    return (f'machine: {host["cpu"]}; {host["cpu_count"]} CPUs; Python {host["python"]}; '
            f'numpy {host["numpy"]}; {host["rmw"]}; domain {domain_id}; load average '
            f'{load_start:.1f} at start, {load_end:.1f} at end')


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
    for marker in ('/site-packages/', '/work/main/'):
        if marker in filename:
            filename = filename.split(marker, 1)[1]
            break
    return f'{filename}:{line}({function})'


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
