"""
Benchmark ``landmark_observer`` against a bare relay node, and its own per-message cost.

Part 1, throughput over DDS, side by side in one run. Two nodes under test, each in
its own process (``multiprocessing`` with the 'spawn' start method) with its own
``SingleThreadedExecutor``, both alive for the whole run, in their own namespaces of
one private ROS domain:

- ``LandmarkObserver`` (namespace ``bench_observer``);
- a relay (namespace ``bench_relay``): subscribes PointCloud2 on ``observations`` and
  republishes the message unchanged on ``landmarks``. Same QoS as the observer:
  best-effort sensor-data input with depth ``input_depth``, reliable output with the
  observer's default ``output_depth``.

Method: closed loop with a window, measured at the driver. The driver (this process)
keeps at most ``W`` observation messages in flight per node and sends the next one
each time an output arrives on ``landmarks`` (reliable subscription); throughput is
outputs per second over a fixed wall time after a warm-up. ``W`` (default 8) is below
the input queue depth, so best effort does not drop messages in the queue and the
node never waits for input: it is the bottleneck. To keep the driver much cheaper
than either node, it does not use an executor: it waits on an rcl wait set, takes
the outputs as serialized bytes and publishes pre-serialized observations, a few
tens of microseconds per message against the ~300 us of one rclpy callback. The
CPU use of the node process (all its threads, from /proc) and of the driver are
printed next to each figure: the node should be near 100 % of one core. A lost
message (no output for 0.25 s) is written off and the window refilled; losses are
printed. Messages of 1, 10 and 100 rows, and the relay and observer runs alternate
in each of ``--reps`` rounds; the tables give the median of the rounds, the ratio
the median of the per-round ratios.

Where a node's time goes, per message: each node process wraps its observation
callback and its output publish and reads the CPU time of its executor thread
(``time.thread_time``) around them, so the report splits the CPU cost of a message
into callback (the node's code), publish (to the driver's reliable subscription)
and executor (the rest: wait-set upkeep, take, deserialization). The observer takes
the messages already waiting in its queue in one callback (up to
``max_batch_messages``) and publishes one output per input, so these are divided by
the messages handled (its ``observation_messages_in`` counter; the relay's
callbacks), not by the callbacks; the messages per callback are printed. CPU times
do not count the time the thread waits for a core, so they hold when other
processes load the machine; the CPU-time ratio relay/observer is what the msg/s
ratio would be on otherwise idle cores.

Poses: before the runs, 101 poses at stamps 100.00 s to 101.00 s every 10 ms are
published in one burst on the observer's ``pose`` topic, reliable with depth 1000
(the observer's pose subscription is made reliable with depth 1000 through its QoS
override parameters; its observation subscription keeps the sensor-data QoS), and
the driver waits for the observer's ``/diagnostics`` to report all of them in its
pose buffer (10 s of history by default, so none expires). Observation stamps cycle
between the poses, so every observation is interpolated and processed at once.

Part 2, the observer's own processing per message, without executor and DDS: in this
process, ``node.on_observations(msg)`` is called directly in a tight loop on
deserialized messages, with the pose buffer filled and a real publisher without
subscriber; best and median of several blocks. Then a breakdown at 100 rows: the
functions the node calls (decode ``read_columns``, pose lookup, noise ``R``, the
core ``landmarks_from_rows`` with its row checks and ``landmark_to_world``, encode
``landmark_message``, ``publish``) are wrapped with ``time.perf_counter`` in this
process only; what remains is the node's own bookkeeping. Last, a cProfile of the
same loop: top functions by own time, and own time by package.

Targets are printed with PASS/FAIL; the script exits 0 whatever the result. The last
line is machine-readable::

    RESULT bench_observer key=value ...

Run from the repository root in the dev venv (``make bench``):
``python bench/bench_observer.py [--reps 4] [--window 8] [--measure 1.0]``.
"""

import argparse
import cProfile
import multiprocessing
import os
import pstats
import statistics
import sys
import threading
import time
import traceback

# DDS discovery stays on this machine; set before rclpy is imported (the spawned node
# processes import this module too).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import _common  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from landmark_ros.nodes import observer as observer_module  # noqa: E402
from landmark_ros.nodes.observer import input_qos, LandmarkObserver, output_qos  # noqa: E402
from landmark_ros.pipeline import rows as observations_module  # noqa: E402
from landmark_ros.pipeline.config import ObserverConfig  # noqa: E402
from landmark_ros.ros import schemas  # noqa: E402
from landmark_ros.ros.schemas import observation_message  # noqa: E402
import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

ROWS = (1, 10, 100)
"""Rows per observation message."""

TARGET_RATIO = 0.8
"""Observer message rate at 100 rows, at least this fraction of the relay's."""

TARGET_OWN_US = 100.0
"""Observer's own processing per 100-row message, without executor [us]."""

RELAY_NS = 'bench_relay'
OBSERVER_NS = 'bench_observer'
KINDS = ('relay', 'observer')
NAMESPACES = {'relay': RELAY_NS, 'observer': OBSERVER_NS}

POSE_T0_S = 100.0
POSE_STEP_S = 0.01
POSE_COUNT = 101
POSE_DEPTH = 1000
WORLD_FRAME = ObserverConfig().world_frame
SENSOR_FRAME = 'bench_sensor'
MESSAGES_PER_SIZE = 64
"""Distinct pre-built observation messages per size, sent in turn."""

STALL_S = 0.25
"""No output for this long with messages in flight: they are written off as lost."""


# --- Messages. ------------------------------------------------------------------

def pose_message(stamp_s, pose, P_pose):
    """Return a PoseWithCovarianceStamped for a planar pose and its 3x3 covariance."""
    return schemas.pose_message(stamp_s, pose, P_pose, WORLD_FRAME)


def pose_messages():
    """Return the pose stream: ``POSE_COUNT`` poses on a slow arc, every 10 ms."""
    P_pose = np.array([[0.02, 0.005, 0.0], [0.005, 0.03, 0.001], [0.0, 0.001, 0.002]])
    result = []
    for k in range(POSE_COUNT):
        t = k * POSE_STEP_S
        result.append(pose_message(POSE_T0_S + t, (1.0 + t, 2.0 + 0.5 * t, 0.3 + 0.2 * t),
                                   P_pose))
    return result


def observation_payloads(rows, count=MESSAGES_PER_SIZE, seed=0):
    """
    Return serialized ``observations`` clouds of ``rows`` rows each.

    Stamps lie strictly between the poses' first and last stamps, off the pose grid,
    so each observation is interpolated; every row is valid.

    """
    rng = np.random.default_rng(seed + rows)
    span = (POSE_COUNT - 1) * POSE_STEP_S
    result = []
    for i in range(count):
        stamp_s = POSE_T0_S + 0.0037 + (span - 0.01) * i / count
        z = np.column_stack([rng.uniform(0.5, 30.0, rows), rng.uniform(-np.pi, np.pi, rows)])
        ids = rng.integers(0, 1000, rows)
        msg = observation_message(schemas.make_header(stamp_s, SENSOR_FRAME), ids, z)
        result.append(serialize_message(msg))
    return result


# --- Nodes under test, each in its own process. -----------------------------------

def observer_overrides(namespace, input_depth):
    """Return the observer's parameters: input depth, reliable deep pose input."""
    topic = f'/{namespace}/pose'
    return [
        Parameter('input_depth', value=input_depth),
        Parameter(f'qos_overrides.{topic}.subscription.reliability', value='reliable'),
        Parameter(f'qos_overrides.{topic}.subscription.depth', value=POSE_DEPTH),
    ]


class _Probe:
    """
    Count the observation callbacks of a node and take CPU times of its main thread.

    ``thread_s`` is the thread's CPU time at the end of the last callback, so that
    its differences over whole callbacks give the CPU cost of the messages they
    handled, executor included, whatever else runs on the machine; ``callback_s``
    and ``publish_s`` are the thread's CPU time inside the callback and inside its
    output publishes. One observer callback may handle several messages (those
    already waiting in its queue), so ``messages`` counts the messages handled (the
    node's ``messages()``: the observer's ``observation_messages_in`` counter, the
    relay's callbacks) and ``publishes`` the outputs; per-message figures divide by
    ``messages``, not by ``callbacks``.
    """

    def __init__(self, subscription, publisher, messages):
        self.callbacks = 0
        self.publishes = 0
        self.callback_s = 0.0
        self.publish_s = 0.0
        self.thread_s = time.thread_time()
        self.messages = messages
        callback, publish = subscription.callback, publisher.publish

        def timed_callback(msg):
            start = time.thread_time()
            try:
                callback(msg)
            finally:
                self.thread_s = time.thread_time()
                self.callback_s += self.thread_s - start
                self.callbacks += 1

        def timed_publish(msg):
            start = time.thread_time()
            try:
                publish(msg)
            finally:
                self.publish_s += time.thread_time() - start
                self.publishes += 1

        subscription.callback = timed_callback
        publisher.publish = timed_publish

    def snapshot(self):
        """Return the counts and times so far."""
        return {'callbacks': self.callbacks, 'messages': self.messages(),
                'publishes': self.publishes, 'callback_s': self.callback_s,
                'publish_s': self.publish_s, 'thread_s': self.thread_s}


def _subscription(node, topic_suffix):
    for subscription in node.subscriptions:
        if subscription.topic_name.endswith(topic_suffix):
            return subscription
    raise RuntimeError(f'{node.get_name()} has no subscription on *{topic_suffix}')


def serve(kind, domain_id, input_depth, conn):
    """
    Run one node under test until told to stop (process entry point).

    Sends ``('ready', pid)`` once spinning. A listener thread answers ``'snap'`` with
    ``('snap', counts)`` (see ``_Probe``) and on anything else stops the executor;
    the process then sends ``('done', stats)``. Failures send ``('error', text)``.
    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = executor = listener = None
    stop = threading.Event()
    try:
        namespace = NAMESPACES[kind]
        if kind == 'observer':
            node = LandmarkObserver(context=context, namespace=namespace,
                                    parameter_overrides=observer_overrides(namespace,
                                                                           input_depth))
            publisher = node.landmark_pub

            def messages():
                return node.counters.counts['observation_messages_in']
        else:
            node = _common.relay('observations', input_qos(input_depth), 'landmarks',
                                 output_qos(ObserverConfig().output_depth),
                                 context=context, namespace=namespace)
            publisher = node.publisher

            def messages():
                return node.count
        probe = _Probe(_subscription(node, '/observations'), publisher, messages)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def listen():
            while True:
                try:
                    request = conn.recv()
                except (EOFError, OSError):
                    request = 'stop'
                if request != 'snap':
                    stop.set()
                    executor.wake()
                    return
                conn.send(('snap', probe.snapshot()))

        conn.send(('ready', os.getpid()))
        listener = threading.Thread(target=listen, name='bench_listener')
        listener.start()
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
        listener.join()
        if kind == 'observer':
            stats = dict(node.counters.counts)
            stats['pose_buffer_size'] = len(node.poses)
            stats['pending_messages'] = len(node.pending)
        else:
            stats = {'messages': node.count}
        stats['peak_rss_kb'] = _common.vm_hwm_kb()
        conn.send(('done', stats))
    except Exception:  # reported to the driver, which prints it
        conn.send(('error', traceback.format_exc()))
    finally:
        if listener is not None and listener.is_alive():
            stop.set()
            listener.join(5.0)
        _common.shutdown(executor, node, context, conn)


class Server(_common.Server):
    """A node under test in a spawned process, with its control pipe."""

    def __init__(self, mp_context, kind, domain_id, input_depth):
        super().__init__(mp_context, kind, serve, (kind, domain_id, input_depth))

    def snapshot(self, timeout=2.0):
        """Return the node's callback counts and times (see ``_Probe``)."""
        self.conn.send('snap')
        if not self.conn.poll(timeout):
            raise RuntimeError(f'{self.kind} node did not answer')
        tag, value = self.conn.recv()
        if tag != 'snap':
            raise RuntimeError(f'{self.kind} node failed:\n{value}')
        return value

    def request_stop(self):
        """Send ``'stop'`` if the process runs; return whether it did."""
        if not self.process.is_alive():
            return False
        self.conn.send('stop')
        return True


# --- The driver: no executor, an rcl wait set and serialized messages. -------------

def make_target(node, kind, input_depth, window):
    """Return the driver's publisher and raw output subscription for one node under test."""
    namespace = NAMESPACES[kind]
    publisher = node.create_publisher(PointCloud2, f'/{namespace}/observations',
                                      input_qos(input_depth))
    depth = max(ObserverConfig().output_depth, 2 * window)
    subscription = node.create_subscription(PointCloud2, f'/{namespace}/landmarks',
                                            lambda _: None, output_qos(depth), raw=True)
    return _common.Target(node, kind, publisher, subscription)


def send_poses(node, timeout):
    """
    Publish the pose stream to the observer; wait for its diagnostics to show them.

    Returns
    -------
    int or None
        The pose buffer size the observer reports, None if no report came.

    """
    reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=POSE_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(PoseWithCovarianceStamped, f'/{OBSERVER_NS}/pose',
                                      reliable)
    diagnostics = node.create_subscription(DiagnosticArray, '/diagnostics', lambda _: None,
                                           10)
    try:
        if not _common.wait_for_match([(publisher, diagnostics)], timeout):
            return None
        for msg in pose_messages():
            publisher.publish(msg)
        deadline = time.monotonic() + timeout
        size = None
        while time.monotonic() < deadline:
            for array in _common.take(_common.wait_set_for(node), diagnostics, DiagnosticArray,
                                      False, 0.1):
                for status in array.status:
                    if OBSERVER_NS not in status.name:
                        continue
                    values = {kv.key: kv.value for kv in status.values}
                    if 'pose_buffer_size' in values:
                        size = int(values['pose_buffer_size'])
            if size is not None and size >= POSE_COUNT:
                break
        return size
    finally:
        node.destroy_publisher(publisher)
        node.destroy_subscription(diagnostics)


def run_window(target, payloads, rows, server, window, warmup_s, measure_s):
    """
    Drive one node closed-loop with ``window`` messages in flight; measure outputs/s.

    Returns
    -------
    dict
        ``msg_per_s``; ``node_cpu`` and ``driver_cpu`` (all threads, fractions of one
        core); from the node's main thread: ``thread_share`` (its CPU time over wall
        time), ``cpu_us`` (its CPU time per message handled), ``callback_us`` (CPU time
        in the observation callback, publish included) and ``publish_us``, per message;
        ``messages_per_callback``, ``publishes_per_message``; ``lost`` (messages
        written off); ``outputs_ok`` (the last output has ``rows`` rows).

    """
    state = {'sent': 0, 'in_flight': 0}

    def refill():
        while state['in_flight'] < window:
            target.publisher.publish(payloads[state['sent'] % len(payloads)])
            state['sent'] += 1
            state['in_flight'] += 1

    received = lost = 0
    last = None
    start = time.perf_counter()
    measure_at, end_at = start + warmup_s, start + warmup_s + measure_s
    mark = probe = None
    last_progress = start
    refill()
    while True:
        now = time.perf_counter()
        if mark is None and now >= measure_at:
            mark = (now, received, _common.process_cpu_s(server.pid), time.process_time())
            probe = server.snapshot()
        if now >= end_at:
            break
        count, raw = target.wait(0.005)
        now = time.perf_counter()
        if count:
            received += count
            last = raw
            state['in_flight'] -= count
            last_progress = now
            refill()
        elif state['in_flight'] > 0 and now - last_progress > STALL_S:
            lost += state['in_flight']
            state['in_flight'] = 0
            last_progress = now
            refill()
    end = (time.perf_counter(), received, _common.process_cpu_s(server.pid), time.process_time())
    end_probe = server.snapshot()
    # Let the messages in flight come back so that the next run starts clean.
    deadline = time.perf_counter() + 1.0
    while state['in_flight'] > 0 and time.perf_counter() < deadline:
        count, _ = target.wait(0.01)
        state['in_flight'] -= count
    lost += max(state['in_flight'], 0)
    wall = end[0] - mark[0]
    # Per message, not per callback: an observer callback handles every message
    # already waiting (up to max_batch_messages).
    callbacks = max(end_probe['callbacks'] - probe['callbacks'], 1)
    messages = max(end_probe['messages'] - probe['messages'], 1)
    thread_s = end_probe['thread_s'] - probe['thread_s']
    outputs_ok = False
    if last is not None:
        outputs_ok = deserialize_message(last, PointCloud2).width == rows
    return {
        'msg_per_s': (end[1] - mark[1]) / wall,
        'node_cpu': (end[2] - mark[2]) / wall,
        'driver_cpu': (end[3] - mark[3]) / wall,
        'thread_share': thread_s / wall,
        'cpu_us': thread_s / messages * 1e6,
        'callback_us': (end_probe['callback_s'] - probe['callback_s']) / messages * 1e6,
        'publish_us': (end_probe['publish_s'] - probe['publish_s']) / messages * 1e6,
        'messages_per_callback': messages / callbacks,
        'publishes_per_message': (end_probe['publishes'] - probe['publishes']) / messages,
        'lost': lost,
        'outputs_ok': outputs_ok,
    }


def throughput(args, domain_id, deadline_s):
    """
    Start both nodes, feed them, and return the runs and the nodes' final statistics.

    Returns
    -------
    runs : dict
        ``(kind, rows) -> list of run_window results``.
    info : dict
        ``pose_buffer_size`` (reported by the observer before the runs),
        ``observer_stats``, ``relay_stats``.

    """
    mp_context = multiprocessing.get_context('spawn')
    servers = {}
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = None
    runs = {(kind, rows): [] for kind in KINDS for rows in ROWS}
    info = {}
    try:
        for kind in KINDS:
            servers[kind] = Server(mp_context, kind, domain_id, args.input_depth)
        for server in servers.values():
            server.wait_ready(30.0)
        node = rclpy.create_node('bench_observer_driver', context=context)
        targets = {kind: make_target(node, kind, args.input_depth, args.window)
                   for kind in KINDS}
        pairs = [(t.publisher, t.subscription) for t in targets.values()]
        if not _common.wait_for_match(pairs, 10.0):
            raise RuntimeError('driver and nodes did not match within 10 s')
        info['pose_buffer_size'] = send_poses(node, 5.0)
        payloads = {rows: observation_payloads(rows) for rows in ROWS}
        for rep in range(args.reps):
            for rows in ROWS:
                order = KINDS if rep % 2 == 0 else KINDS[::-1]
                for kind in order:
                    runs[kind, rows].append(run_window(
                        targets[kind], payloads[rows], rows, servers[kind], args.window,
                        args.warmup, args.measure))
            if time.perf_counter() > deadline_s:
                print(f'(time budget reached after {rep + 1} rounds)')
                break
    finally:
        for server in servers.values():
            server.stop()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    info['observer_stats'] = servers['observer'].stats if 'observer' in servers else None
    info['relay_stats'] = servers['relay'].stats if 'relay' in servers else None
    return runs, info


# --- The observer's own processing, in-process. ----------------------------------

def time_blocks(function, messages, calls, blocks):
    """Call ``function`` on the messages in turn; return per-call seconds of each block."""
    per_block = max(1, calls // blocks)
    for msg in messages[:16]:
        function(msg)
    result = []
    count = len(messages)
    for _ in range(blocks):
        start = time.perf_counter()
        for i in range(per_block):
            function(messages[i % count])
        result.append((time.perf_counter() - start) / per_block)
    return result


class _Timed:
    """Wrap a callable and accumulate its wall time."""

    def __init__(self, function):
        self.function = function
        self.seconds = 0.0
        self.calls = 0

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.function(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start
            self.calls += 1


BREAKDOWN = (
    # (label, owner, names: the first one the owner has is wrapped, level)
    ('decode', 'module', ('read_columns',), 0),
    ('pose lookup + interpolation', 'poses', ('lookup',), 0),
    ('noise R', 'module', ('observation_noise',), 0),
    ('core', 'module', ('landmarks_from_rows',), 0),
    ('row checks', 'observations', ('row_problems',), 1),
    ('to world', 'observations', ('landmark_to_world', 'landmark_to_world_dependent'), 1),
    ('encode', 'module', ('landmark_message',), 0),
    ('publish, no subscriber', 'landmark_pub', ('publish',), 0),
)
"""Pieces of ``on_observations`` timed by ``breakdown``: what the node module calls,
and (level 1) what ``landmarks_from_rows`` calls; names missing after a refactor are
skipped."""


def breakdown(node, messages, calls):
    """
    Time the pieces of ``on_observations`` by wrapping what the node calls.

    Returns
    -------
    total_s : float
        Per-message time of the instrumented loop.
    pieces : list of (label, level, seconds per message)
        Pieces the node calls; what is not in a level-0 piece is the node's own
        bookkeeping.

    """
    owners = {'module': observer_module, 'observations': observations_module,
              'poses': node.poses, 'landmark_pub': node.landmark_pub}
    patched = []
    try:
        for label, where, names, level in BREAKDOWN:
            owner = owners[where]
            name = next((name for name in names if hasattr(owner, name)), None)
            if name is None:
                continue
            timed = _Timed(getattr(owner, name))
            label = label if where in ('poses', 'landmark_pub') else f'{label}  {name}'
            patched.append((owner, name, label, level, timed))
            setattr(owner, name, timed)
        for msg in messages[:16]:
            node.on_observations(msg)
        for *_, timed in patched:
            timed.seconds, timed.calls = 0.0, 0
        start = time.perf_counter()
        for i in range(calls):
            node.on_observations(messages[i % len(messages)])
        total = (time.perf_counter() - start) / calls
    finally:
        for owner, name, _, _, timed in reversed(patched):
            if owner is node.poses or owner is node.landmark_pub:
                delattr(owner, name)
            else:
                setattr(owner, name, timed.function)
    return total, [(label, level, timed.seconds / calls)
                   for _, _, label, level, timed in patched if timed.calls]


def _package(key):
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


def profile(node, messages, calls, top):
    """
    Profile ``on_observations``; return its top functions and own time by package.

    Returns
    -------
    functions : list of (where, tottime_us, cumtime_us, calls per message)
    packages : list of (package, tottime_us)
    total_us : float
        Total own time per message under the profiler.
    calls_per_message : float
        Function calls the profiler saw per message.

    """
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(calls):
        node.on_observations(messages[i % len(messages)])
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    entries = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)
    functions = [(_common.profile_where(key), tt / calls * 1e6, ct / calls * 1e6, nc / calls)
                 for key, (_, nc, tt, ct, _) in entries[:top]]
    packages = {}
    for key, (_, _, tt, _, _) in stats.items():
        name = _package(key)
        packages[name] = packages.get(name, 0.0) + tt / calls * 1e6
    total = sum(packages.values())
    calls_per_message = sum(nc for _, nc, _, _, _ in stats.values()) / calls
    return (functions, sorted(packages.items(), key=lambda item: -item[1]), total,
            calls_per_message)


def own_processing(args, domain_id):
    """
    Time ``LandmarkObserver.on_observations`` in-process; break it down at 100 rows.

    Returns
    -------
    dict
        ``per_rows`` (rows -> (best_s, median_s)), ``breakdown`` (see ``breakdown``),
        ``profile`` (see ``profile``), ``counts_ok``.

    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = None
    try:
        node = LandmarkObserver(context=context, namespace='bench_inproc')
        for msg in pose_messages():
            node.on_pose(msg)
        if len(node.poses) != POSE_COUNT:
            raise RuntimeError(f'pose buffer holds {len(node.poses)} poses, '
                               f'expected {POSE_COUNT}')
        per_rows = {}
        messages = {}
        for rows in ROWS:
            messages[rows] = [deserialize_message(p, PointCloud2)
                              for p in observation_payloads(rows)]
            before = node.counters['landmarks_out']
            blocks = time_blocks(node.on_observations, messages[rows], args.inproc_calls,
                                 args.inproc_blocks)
            calls = 16 + len(blocks) * max(1, args.inproc_calls // args.inproc_blocks)
            per_rows[rows] = (min(blocks), statistics.median(blocks),
                              node.counters['landmarks_out'] - before == calls * rows)
        big = max(ROWS)
        return {
            'per_rows': per_rows,
            'breakdown': breakdown(node, messages[big], args.inproc_calls),
            'profile': profile(node, messages[big], args.profile_calls, args.top),
            'pending_ok': not node.pending,
        }
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


# --- Report. ------------------------------------------------------------------------

def _median(runs, key):
    return _common.median_of(runs, key)


def main(argv=None):
    """
    Run the benchmark, print the report and return the figures.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments without the program name; ``None`` reads ``sys.argv``.

    Returns
    -------
    dict
        ``throughput`` ((kind, rows) -> median msg/s), ``ratio`` (rows -> observer /
        relay), ``own_us`` (rows -> best us per message), ``targets`` (name -> bool)
        and ``seconds``.

    """
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--reps', type=int, default=4,
                        help='rounds of relay/observer runs at every size (default 4)')
    parser.add_argument('--window', type=int, default=8,
                        help='messages in flight per node (default 8)')
    parser.add_argument('--warmup', type=float, default=0.3,
                        help='seconds of each run before measuring (default 0.3)')
    parser.add_argument('--measure', type=float, default=1.0,
                        help='measured seconds of each run (default 1.0)')
    parser.add_argument('--input-depth', type=int, default=ObserverConfig().input_depth,
                        help='input queue depth of both nodes (default: the observer '
                        'default)')
    parser.add_argument('--inproc-calls', type=int, default=3000,
                        help='direct on_observations calls per size (default 3000)')
    parser.add_argument('--inproc-blocks', type=int, default=12,
                        help='blocks the direct calls are split into (default 12)')
    parser.add_argument('--profile-calls', type=int, default=1000,
                        help='calls under cProfile (default 1000)')
    parser.add_argument('--top', type=int, default=12,
                        help='functions shown from the profile (default 12)')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS domain ID of the throughput runs, 0-232 (default 215-231 '
                        'from the PID); the in-process part uses the next one')
    parser.add_argument('--budget', type=float, default=50.0,
                        help='stop starting new rounds after this many seconds (default 50)')
    args = parser.parse_args(argv)
    if args.window >= args.input_depth:
        parser.error('--window must be below --input-depth, or best effort drops messages')
    # 215-232 are free of the tests' range (1-200) and valid for the DDS port mapping.
    domain_id = args.domain if args.domain is not None else 215 + os.getpid() % 17
    started = time.perf_counter()
    host = _common.machine()
    load_start = os.getloadavg()[0]

    runs, info = throughput(args, domain_id, started + args.budget - 15.0)
    own = own_processing(args, domain_id + 1 if domain_id < 232 else domain_id - 1)
    seconds = time.perf_counter() - started
    load_end = os.getloadavg()[0]

    relay = {rows: _median(runs['relay', rows], 'msg_per_s') for rows in ROWS}
    observer = {rows: _median(runs['observer', rows], 'msg_per_s') for rows in ROWS}
    # Relay and observer runs of a round are next to each other in time: the median of
    # the per-round ratios cancels slow changes of the machine's load.
    ratio = {rows: statistics.median(o['msg_per_s'] / r['msg_per_s'] for r, o in zip(
        runs['relay', rows], runs['observer', rows])) for rows in ROWS}
    own_us = {rows: own['per_rows'][rows][0] * 1e6 for rows in ROWS}
    own_median_us = {rows: own['per_rows'][rows][1] * 1e6 for rows in ROWS}
    big = max(ROWS)
    lost = sum(run['lost'] for key in runs for run in runs[key])
    outputs_ok = all(run['outputs_ok'] for key in runs for run in runs[key])
    counts_ok = all(ok for _, _, ok in own['per_rows'].values()) and own['pending_ok']
    targets = {
        'ratio_100': ratio[big] >= TARGET_RATIO,
        'own_us_100': own_us[big] < TARGET_OWN_US,
    }
    rounds = len(runs['relay', ROWS[0]])

    lines = [
        f'bench_observer: landmark_observer vs a bare relay node, closed loop, '
        f'window {args.window}, input depth {args.input_depth}, {rounds} rounds of '
        f'{args.warmup:g} s warm-up + {args.measure:g} s per run (medians)',
        _common.machine_line(host, domain_id, load_start, load_end),
        f'poses: {POSE_COUNT} sent in a burst, observer reported '
        f'{info.get("pose_buffer_size")} in its buffer',
        '',
        'rows/msg | relay msg/s | observer msg/s | ratio | observer obs/s | '
        'CPU relay / observer / driver',
        '(rates: medians of the rounds; ratio: median of the per-round ratios; CPU: one '
        'core = 100 %)',
    ]
    for rows in ROWS:
        cpu = (f'{_median(runs["relay", rows], "node_cpu") * 100:4.0f} % / '
               f'{_median(runs["observer", rows], "node_cpu") * 100:4.0f} % / '
               f'{_median(runs["observer", rows], "driver_cpu") * 100:4.0f} %')
        lines.append(f'{rows:8d} | {relay[rows]:11.0f} | {observer[rows]:14.0f} | '
                     f'{ratio[rows]:5.2f} | {observer[rows] * rows:14.0f} | {cpu}')
    lines += [
        '',
        "per message handled, CPU time of the node's executor thread [us] (robust to other "
        'load): total; callback = observation callback, publish included; executor = '
        'total - callback (wait set, take, deserialize); share = thread CPU / wall time; '
        'msg/cb = messages handled per callback',
        'rows/msg | node     | wall/msg | CPU/msg | callback | publish | executor | share | '
        'msg/cb',
    ]
    cpu_ratio = {}
    for rows in ROWS:
        for kind, rate in (('relay', relay[rows]), ('observer', observer[rows])):
            cpu = _median(runs[kind, rows], 'cpu_us')
            callback = _median(runs[kind, rows], 'callback_us')
            lines.append(f'{rows:8d} | {kind:8s} | {1e6 / rate:8.0f} | {cpu:7.0f} | '
                         f'{callback:8.0f} | {_median(runs[kind, rows], "publish_us"):7.0f} | '
                         f'{cpu - callback:8.0f} | '
                         f'{_median(runs[kind, rows], "thread_share") * 100:3.0f} % | '
                         f'{_median(runs[kind, rows], "messages_per_callback"):6.2f}')
        cpu_ratio[rows] = (_median(runs['relay', rows], 'cpu_us')
                           / _median(runs['observer', rows], 'cpu_us'))
    lines.append('CPU-time ratio relay/observer per message (what the msg/s ratio would be '
                 'on idle cores): ' + ', '.join(f'{rows} rows {cpu_ratio[rows]:.2f}'
                                                for rows in ROWS))
    lines.append('each round (msg/s, relay / observer): ' + '; '.join(
        f'{rows} rows: ' + ', '.join(
            f'{r["msg_per_s"]:.0f}/{o["msg_per_s"]:.0f}'
            for r, o in zip(runs['relay', rows], runs['observer', rows]))
        for rows in ROWS))
    publishes_ok = all(abs(run['publishes_per_message'] - 1.0) < 0.02
                       for key in runs for run in runs[key])
    lines.append(f'lost messages {lost}; outputs have the rows sent: '
                 f'{_common.verdict(outputs_ok)}; one publish per message handled: '
                 f'{_common.verdict(publishes_ok)}')
    obs_stats = info.get('observer_stats') or {}
    problems = {k: v for k, v in obs_stats.items()
                if k not in observer_module.THROUGHPUT_COUNTERS
                and k not in ('pose_buffer_size', 'pending_messages', 'peak_rss_kb') and v}
    lines.append(f'observer counters: {obs_stats.get("observation_messages_in")} messages '
                 f'in, {obs_stats.get("landmarks_out")} landmarks out, rejections '
                 f'{problems or "none"}')
    peak_mb = {kind: ((info.get(f'{kind}_stats') or {}).get('peak_rss_kb') or 0) / 1024
               for kind in KINDS}
    lines.append('peak memory (VmHWM of the node processes): ' + ', '.join(
        f'{kind} {peak_mb[kind]:.0f} MB' for kind in KINDS))
    lines += [
        '',
        'observer own processing, on_observations called directly (no executor, '
        f'publisher without subscriber), best / median of {args.inproc_blocks} blocks:',
    ]
    for rows in ROWS:
        lines.append(f'  {rows:4d} rows: {own_us[rows]:7.1f} / {own_median_us[rows]:7.1f} '
                     'us/msg  (throughput runs: callback '
                     f'{_median(runs["observer", rows], "callback_us"):4.0f} us CPU/msg, its '
                     f'publish to a subscriber '
                     f'{_median(runs["observer", rows], "publish_us"):3.0f} us)')
    total_s, pieces = own['breakdown']
    lines.append(f'breakdown at {big} rows (instrumented loop {total_s * 1e6:.1f} us/msg):')
    accounted = 0.0
    for label, level, piece_s in pieces:
        if level == 0:
            accounted += piece_s
        lines.append(f'  {"  " * level}{label:<{40 - 2 * level}} {piece_s * 1e6:7.1f} us '
                     f'{piece_s / total_s * 100:5.1f} %')
    rest = total_s - accounted
    lines.append(f'  {"node bookkeeping (the rest)":<40} {rest * 1e6:7.1f} us '
                 f'{rest / total_s * 100:5.1f} %')
    functions, packages, profiled_us, calls_per_message = own['profile']
    lines.append(f'cProfile at {big} rows, {args.profile_calls} calls ({profiled_us:.0f} '
                 f'us/msg under the profiler, {calls_per_message:.0f} function calls/msg); '
                 'own time by package:')
    lines.append('  ' + ', '.join(f'{name} {us:.0f} us' for name, us in packages[:8]))
    lines.append('  top functions by own time: tottime us/msg, cumtime us/msg, '
                 'calls/msg, function')
    for where, tottime, cumtime, ncalls in functions:
        lines.append(f'  {tottime:7.1f} {cumtime:8.1f} {ncalls:5.1f}  {where}')
    lines += [
        '',
        f'targets: observer msg/s at {big} rows >= {TARGET_RATIO:.0%} of relay '
        f'({ratio[big]:.2f}): {_common.verdict(targets["ratio_100"])}; own processing at {big} '
        f'rows < {TARGET_OWN_US:g} us ({own_us[big]:.1f} us): '
        f'{_common.verdict(targets["own_us_100"])}; in-process counts '
        f'{_common.verdict(counts_ok)}; run time {seconds:.1f} s',
        'RESULT bench_observer'
        + ''.join(f' relay_msg_per_s_{rows}={relay[rows]:.6g}'
                  f' observer_msg_per_s_{rows}={observer[rows]:.6g}'
                  f' ratio_{rows}={ratio[rows]:.4g}' for rows in ROWS)
        + f' observer_obs_per_s_{big}={observer[big] * big:.6g}'
        + ''.join(f' cpu_ratio_{rows}={cpu_ratio[rows]:.4g}' for rows in ROWS)
        + f' relay_cpu_us_{big}={_median(runs["relay", big], "cpu_us"):.4g}'
        f' observer_cpu_us_{big}={_median(runs["observer", big], "cpu_us"):.4g}'
        f' observer_msg_per_callback_{big}='
        f'{_median(runs["observer", big], "messages_per_callback"):.3g}'
        + ''.join(f' own_us_{rows}={own_us[rows]:.4g}' for rows in ROWS)
        + ''.join(f' peak_rss_{kind}_mb={peak_mb[kind]:.4g}' for kind in KINDS)
        + f' window={args.window} rounds={rounds} lost={lost}'
        f' cpus={host["cpu_count"]} pass={int(all(targets.values()))}',
    ]
    print('\n'.join(lines))
    sys.stdout.flush()
    return {
        'throughput': {**{('relay', r): relay[r] for r in ROWS},
                       **{('observer', r): observer[r] for r in ROWS}},
        'ratio': ratio,
        'own_us': own_us,
        'targets': targets,
        'seconds': seconds,
    }


if __name__ == '__main__':
    main()
    sys.exit(0)
