"""
Benchmark landmark fusion: ``LandmarkMap.update`` and the ``landmark_fuser`` node.

Part 1, core fusion, in this process. A ``LandmarkMap`` is warmed with two
consistent observations of each of 1,000 landmarks (all confirmed, through the
map's own tentative path), then fed batches of 100, 1,000, 10,000 and 100,000 rows
with random landmark IDs among the 1,000, for each fusion method. The observations
are realistic and consistent: a robot 2-20 m from the landmark, its pose estimate
drawn from a full 3x3 pose covariance, range and bearing noise from a full 2x2
``R``; ``landmark_to_world_dependent`` gives the world position, its full 2x2
covariance and the dependent (pose) part. Calls are made the way the node makes
them: per-row source names (three robots) and stamps. Every timed call fuses new
rows into a copy of the warmed map; best, median and worst of several calls.
For context, the textbook way on a subset: a per-observation Python loop that
looks each landmark up in a dict, gates it and calls ``gaussian.fuse`` (or
``covariance_intersection``, ``split_covariance_intersection``) on single 2-vectors
and 2x2 matrices; its result is checked against the map's for ``independent`` and
``covariance_intersection`` (the map's ``split_covariance_intersection`` may keep
per-source sums, which a per-observation loop does not model, so it is only
printed). Every cell also gives a CPU-time rate (rows / ``time.thread_time``), which
waiting for a core does not inflate (on a VM, stolen time still does). Last, a
cProfile of ``update`` for ``independent`` at the fastest batch size.

Part 2, the node over DDS, side by side in one run. Three nodes under test, each in
its own process (``multiprocessing``, 'spawn') with its own
``SingleThreadedExecutor``, all alive for the whole run, in their own namespaces of
one private ROS domain: ``LandmarkFuser`` with ``split_covariance_intersection``
(the default), ``LandmarkFuser`` with ``independent``, and a bare relay
(subscribes PointCloud2 on ``landmarks`` and republishes it unchanged). The fusers'
maps are loaded with the warmed maps of part 1 (1,000 confirmed landmarks). Input
QoS is the fuser's: reliable, keep last, depth ``input_depth`` (100); the relay's
output is reliable with depth 10.

The fuser publishes its map only on a timer, so its rate is measured where it
consumes input: each node process counts the messages its subscription callback
handled (the fuser's own ``messages_in`` counter, the relay's callbacks) and the CPU
time of its executor thread inside the callbacks and timers (``time.thread_time``),
into shared memory the driver reads. The driver (this process, no executor: it
publishes pre-serialized 100-row ``landmarks`` messages) is the same for all three:
closed loop, it keeps ``W`` (default 50, below the input depth, so reliable
keep-last never overwrites) messages sent but not yet handled by the node, polling
every millisecond (it wakes earlier when the relay's output or a fused map
arrives; relay outputs are taken and counted). The node's queue is never empty, so
it is the bottleneck; the driver checks that (polls that found the node idle) and
its own CPU use is printed. Rate = messages handled / wall time over ``--measure``
seconds after ``--warmup``; the runs of the three nodes alternate in each of
``--reps`` rounds; tables give the median of the rounds, the ratios the median of
the per-round ratios.

Fusion lag, two ways: in the fuser process, the time from the last input taken
before a fusion (and from the oldest one) to the end of the ``LandmarkMap.update``
that contains it; end to end, the time from the driver publishing a probe message
(two rows of a new landmark, sent last in each run, behind a full window) to the
first ``fused_landmarks`` message that holds that landmark (this adds the queue,
the ``update_period_s`` timer and the ``publish_rate_hz`` timer).

Part 3, where the fuser's time goes, in this process without executor and DDS: the
fuser's subscription callback on deserialized messages and ``fuse_queued`` every 20
messages (about one timer period at the measured rates), timed and under cProfile,
for both fusion methods.

Peak memory: of each node process its ``VmHWM`` (and ``resource.getrusage``
maxrss, which Linux carries over ``exec`` from the spawning process: the node
processes are therefore spawned early, from a small process), and this process's
maxrss (driver and core part).

Targets are printed with PASS/FAIL; the script exits 0 whatever the result. The last
line is machine-readable::

    RESULT bench_fuser key=value ...

Run from the repository root in the dev venv (``make bench``):
``python bench/bench_fuser.py [--reps 3] [--window 50] [--measure 1.0]``.
"""

import argparse
import copy
import cProfile
import gc
import math
import multiprocessing
import os
import pstats
import resource
import statistics
import sys
import time
import traceback

# DDS discovery stays on this machine; set before rclpy is imported (the spawned node
# processes import this module too).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import _common  # noqa: E402
from landmark_ros.core import gaussian  # noqa: E402
from landmark_ros.core.landmark_map import FUSION_METHODS, LandmarkMap  # noqa: E402
from landmark_ros.core.landmarks import landmark_to_world_dependent  # noqa: E402
from landmark_ros.nodes.fuser import LandmarkFuser, LATCHED  # noqa: E402
from landmark_ros.pipeline.config import FuserConfig  # noqa: E402
from landmark_ros.ros.schemas import landmark_message, make_header, read_landmarks  # noqa: E402
import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.logging import LoggingSeverity  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

LANDMARKS = 1000
"""Confirmed landmarks in the map."""

BATCHES = (100, 1000, 10_000, 100_000)
"""Rows per ``LandmarkMap.update`` call."""

ROBOTS = ('robot1', 'robot2', 'robot3')
"""Source names of the core batches."""

TARGET_OBS_PER_S = 1e6
"""Core target for ``independent`` at its best batch size [observations/s]."""

TARGET_RATIO = 0.8
"""Fuser message rate at 100 rows, at least this fraction of the relay's."""

ROWS_PER_MESSAGE = 100
WORLD_FRAME = FuserConfig().world_frame
DEFAULT_FUSION = FuserConfig().fusion
RELAY_OUTPUT_DEPTH = 10

KINDS = ('relay', 'split_covariance_intersection', 'independent')
"""Nodes under test: the relay and the fuser with two fusion methods."""
NAMESPACES = {'relay': 'bench_relay', 'split_covariance_intersection': 'bench_fuser_sci',
              'independent': 'bench_fuser_ind'}
LABELS = {'relay': 'relay', 'split_covariance_intersection': 'fuser split CI',
          'independent': 'fuser independent'}
SHORT = {'split_covariance_intersection': 'split_ci', 'covariance_intersection': 'ci',
         'independent': 'independent'}

POOL_MESSAGES = 400
"""Distinct pre-serialized messages the driver sends in turn."""

POLL_S = 0.001
STALL_S = 0.5
"""No message handled for this long with messages outstanding: written off as lost."""

AGREEMENT_ATOL = 1e-9
"""Largest difference allowed between the textbook loop's map and the update's."""

MUST_MATCH = ('independent', 'covariance_intersection')
"""Methods whose ``update`` fuses observation by observation, as the loop does; the
map's split CI may keep per-source sums, which the loop does not model."""

PROBE_ID0 = LANDMARKS
"""First landmark ID of the end-to-end lag probes (IDs not in the map)."""


# --- Observations. ---------------------------------------------------------------

def make_world(seed):
    """Return the true positions of the landmarks, shape (LANDMARKS, 2), in a 100 m square."""
    return np.random.default_rng(seed).uniform(-50.0, 50.0, (LANDMARKS, 2))


def observe(truth, ids, rng):
    """
    Return consistent world-frame observations of the landmarks ``ids``.

    Each row: a robot 2-20 m from the landmark with a random heading, its pose
    estimate drawn from a full 3x3 covariance, a range-bearing measurement with a
    full 2x2 noise covariance, placed in the world to first order.

    Returns
    -------
    m : ndarray, shape (N, 2)
    P : ndarray, shape (N, 2, 2)
        Total covariances.
    P_dep : ndarray, shape (N, 2, 2)
        Their dependent (pose) parts.

    """
    n = len(ids)
    r = rng.uniform(2.0, 20.0, n)
    direction = rng.uniform(-np.pi, np.pi, n)
    heading = rng.uniform(-np.pi, np.pi, n)
    pose = np.column_stack([truth[ids, 0] - r * np.cos(direction),
                            truth[ids, 1] - r * np.sin(direction), heading])
    scale = np.array([0.1, 0.1, 0.01]) * rng.uniform(0.5, 2.0, (n, 1))
    A = rng.normal(size=(n, 3, 3)) * scale[:, :, None]
    P_pose = A @ np.swapaxes(A, 1, 2) / 3.0 + 1e-6 * np.eye(3)
    pose_estimate = pose + (np.linalg.cholesky(P_pose) @ rng.normal(size=(n, 3, 1)))[:, :, 0]
    sigma_r, sigma_b = rng.uniform(0.05, 0.2, n), rng.uniform(0.005, 0.02, n)
    rho = rng.uniform(-0.3, 0.3, n)
    R = np.empty((n, 2, 2))
    R[:, 0, 0], R[:, 1, 1] = sigma_r ** 2, sigma_b ** 2
    R[:, 0, 1] = R[:, 1, 0] = rho * sigma_r * sigma_b
    bearing = (direction - heading + np.pi) % (2.0 * np.pi) - np.pi
    z = np.column_stack([r, bearing]) + (np.linalg.cholesky(R) @ rng.normal(
        size=(n, 2, 1)))[:, :, 0]
    return landmark_to_world_dependent(pose_estimate, P_pose, z, R)


def make_pool(truth, n, seed):
    """Return ``n`` observation rows of random landmarks, with sources and stamps."""
    rng = np.random.default_rng(seed)
    ids = rng.integers(0, LANDMARKS, n)
    m, P, P_dep = observe(truth, ids, rng)
    return {'ids': ids, 'm': m, 'P': P, 'P_dep': P_dep,
            'source': np.array(ROBOTS)[rng.integers(0, len(ROBOTS), n)],
            'stamp': 1000.0 + np.arange(n) * 1e-4}


def rows_of(pool, start, count):
    """Return the arguments of ``LandmarkMap.update`` for rows [start, start + count)."""
    part = slice(start, start + count)
    return (pool['ids'][part], pool['m'][part], pool['P'][part], pool['P_dep'][part],
            pool['source'][part], pool['stamp'][part])


def warm_map(fusion, truth, seed):
    """
    Return a map holding every landmark confirmed, and the warm-up's obs/s.

    Two observations per landmark (``min_observations``), fused in one update through
    the map's tentative path; the rare landmark whose two observations fail the gate
    gets more until it is confirmed.
    """
    rng = np.random.default_rng(seed)
    ids = np.tile(np.arange(LANDMARKS), 2)
    landmark_map = LandmarkMap(fusion)
    rows, seconds = 0, 0.0
    for _ in range(10):
        m, P, P_dep = observe(truth, ids, rng)
        start = time.perf_counter()
        landmark_map.update(ids, m, P, P_dep, 'warmup', 0.0)
        seconds += time.perf_counter() - start
        rows += len(ids)
        confirmed = set(landmark_map.snapshot()[0].tolist())
        ids = np.array([i for i in range(LANDMARKS) if i not in confirmed], np.int64)
        if not len(ids):
            return landmark_map, rows / seconds
    raise RuntimeError(f'{fusion}: {len(landmark_map)} landmarks confirmed by the warm-up, '
                       f'expected {LANDMARKS}')


# --- Part 1: core fusion. ----------------------------------------------------------

def time_updates(base, pool, batch, min_calls, min_s, max_s, max_calls):
    """
    Time ``update`` calls of ``batch`` new rows each on a copy of ``base``.

    At least ``min_calls`` calls and ``min_s`` seconds, unless the calls have taken
    ``max_s`` already (then at least one call); at most ``max_calls``.

    Returns
    -------
    seconds : list of float
        Wall time per timed call.
    cpu_seconds : list of float
        CPU time of this thread per timed call (what other load does not inflate).
    gated_out : float
        Fraction of the rows rejected by the gate.

    """
    landmark_map = copy.deepcopy(base)
    size = len(pool['ids'])
    start_row = 0

    def next_rows():
        nonlocal start_row
        if start_row + batch > size:
            start_row = 0
        args = rows_of(pool, start_row, batch)
        start_row += batch
        return args

    if batch <= 1000:
        landmark_map.update(*next_rows())  # untimed: first-call effects
    seconds, cpu_seconds, rejected, rows = [], [], 0, 0
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        began = time.perf_counter()
        while not seconds or (
                len(seconds) < max_calls and time.perf_counter() - began < max_s
                and (len(seconds) < min_calls or time.perf_counter() - began < min_s)):
            args = next_rows()
            start, cpu_start = time.perf_counter(), time.thread_time()
            result = landmark_map.update(*args)
            seconds.append(time.perf_counter() - start)
            cpu_seconds.append(time.thread_time() - cpu_start)
            rejected += sum(result.rejected.values())
            rows += batch
    finally:
        if gc_was_enabled:
            gc.enable()
    return seconds, cpu_seconds, rejected / rows


def textbook_loop(landmark_map, ids, z, R, R_dep, fusion):
    """
    Fuse observations one at a time, the textbook way, with the ``gaussian`` functions.

    A dict maps each landmark ID to its estimate (mean, independent and dependent
    covariance parts); every observation is gated against it (squared Mahalanobis
    distance with ``P + R``, ``np.linalg.solve``) and fused with ``gaussian.fuse``,
    ``gaussian.covariance_intersection`` or ``gaussian.split_covariance_intersection``
    on single 2-vectors and 2x2 matrices.

    Returns
    -------
    dict
        ``id -> (m, P_ind, P_dep)`` after the loop.

    """
    ids_all, m_all, P_all, P_dep_all, _ = landmark_map.snapshot()
    estimates = {int(i): (m, P - P_dep, P_dep)
                 for i, m, P, P_dep in zip(ids_all, m_all, P_all, P_dep_all)}
    threshold = landmark_map.threshold
    zero = np.zeros((2, 2))
    for i in range(len(ids)):
        key = int(ids[i])
        m, P_ind, P_dep = estimates[key]
        d = z[i] - m
        if d @ np.linalg.solve(P_ind + P_dep + R[i], d) > threshold:
            continue
        if fusion == 'independent':
            m, P = gaussian.fuse(m, P_ind + P_dep, z[i], R[i])
            estimates[key] = (m, P, zero)
        elif fusion == 'covariance_intersection':
            m, P = gaussian.covariance_intersection(m, P_ind + P_dep, z[i], R[i])
            estimates[key] = (m, zero, P)
        else:
            estimates[key] = gaussian.split_covariance_intersection(
                m, P_ind, P_dep, z[i], R[i] - R_dep[i], R_dep[i])
    return estimates


def loop_case(base, pool, loop_n, repeats):
    """
    Time the textbook loop on ``loop_n`` rows and compare it with ``update``.

    Returns
    -------
    dict
        ``obs_per_s`` (best of up to ``repeats``, while they take under 0.6 s),
        ``max_abs_diff`` (means and
        covariances, loop against one ``update`` of the same rows).

    """
    ids, z, R, R_dep, source, stamp = rows_of(pool, 0, loop_n)
    best, estimates, spent = float('inf'), None, 0.0
    for _ in range(repeats):
        start = time.perf_counter()
        estimates = textbook_loop(base, ids, z, R, R_dep, base.fusion)
        best = min(best, time.perf_counter() - start)
        spent += time.perf_counter() - start
        if spent > 0.6:
            break
    landmark_map = copy.deepcopy(base)
    landmark_map.update(ids, z, R, R_dep, source, stamp)
    map_ids, m, P, P_dep, _ = landmark_map.snapshot()
    diff = 0.0
    for i, key in enumerate(map_ids.tolist()):
        m_loop, P_ind_loop, P_dep_loop = estimates[key]
        diff = max(diff, float(np.max(np.abs(m[i] - m_loop))),
                   float(np.max(np.abs(P[i] - P_ind_loop - P_dep_loop))),
                   float(np.max(np.abs(P_dep[i] - P_dep_loop))))
    return {'obs_per_s': loop_n / best, 'max_abs_diff': diff}


def profile_calls(function, calls, top):
    """
    Profile ``function(i)`` for ``i`` in ``range(calls)``.

    Returns
    -------
    list of (where, tottime_ms, cumtime_ms, ncalls), per call of ``function``
        The ``top`` functions by own time.
    total_ms : float
        Total own time per call under the profiler.

    """
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(calls):
        function(i)
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    entries = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)
    total = sum(tt for _, _, tt, _, _ in stats.values()) / calls * 1e3
    return ([(_common.profile_where(key), tt / calls * 1e3, ct / calls * 1e3, nc / calls)
             for key, (_, nc, tt, ct, _) in entries[:top]], total)


def core_fusion(args, truth, maps):
    """
    Run part 1.

    Returns
    -------
    dict
        ``cells`` ((method, batch) -> {'best', 'median', 'worst' obs/s, 'calls',
        'gated_out'}), ``loop`` (method -> loop_case), ``profile`` (batch, entries,
        total_ms).

    """
    pool = make_pool(truth, args.pool_rows, args.seed + 1)
    cells = {}
    for method in FUSION_METHODS:
        for batch in BATCHES:
            # Few calls of the big batches: a split-CI call of 100,000 rows takes seconds.
            min_calls = 2 if batch >= 100_000 else 5
            seconds, cpu_seconds, gated_out = time_updates(
                maps[method], pool, batch, min_calls, args.min_seconds, args.max_seconds, 2000)
            rates = sorted(batch / s for s in seconds)
            cells[method, batch] = {'best': rates[-1], 'median': statistics.median(rates),
                                    'worst': rates[0], 'calls': len(rates),
                                    'cpu': statistics.median(batch / s for s in cpu_seconds),
                                    'gated_out': gated_out}
    loop = {method: loop_case(maps[method], pool, args.loop_n, 5) for method in FUSION_METHODS}
    best_batch = max(BATCHES, key=lambda b: cells['independent', b]['best'])
    calls = max(3, min(200, 200_000 // best_batch))
    landmark_map = copy.deepcopy(maps['independent'])
    profile = profile_calls(
        lambda i: landmark_map.update(*rows_of(pool, (i * best_batch) % (
            args.pool_rows - best_batch + 1), best_batch)), calls, args.top)
    return {'cells': cells, 'loop': loop, 'profile': (best_batch, calls) + profile}


# --- Part 2: nodes under test, each in its own process. ----------------------------

# Fields of the shared array a node process writes and the driver reads.
MESSAGES, CALLBACK_S, PUBLISH_S, THREAD_S, FUSE_CALLS, FUSE_S, ROWS_FUSED, MAP_PUB_S, \
    OTHER_S, LAG_SUM, LAG_MAX, LAG_OLDEST_SUM, LAG_OLDEST_MAX, STOP = range(14)
FIELDS = 14


def input_qos(depth):
    """Return the fuser's input QoS: reliable, keep last ``depth``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE)


def instrument_relay(node, shared):
    """Count the relay's callbacks and time them and its publish (thread CPU time)."""
    subscription, callback, publish = node.subscription, node.subscription.callback, \
        node.publisher.publish

    def timed_callback(msg):
        start = time.thread_time()
        try:
            callback(msg)
        finally:
            now = time.thread_time()
            shared[CALLBACK_S] += now - start
            shared[THREAD_S] = now
            shared[MESSAGES] = node.count

    def timed_publish(msg):
        start = time.thread_time()
        try:
            publish(msg)
        finally:
            shared[PUBLISH_S] += time.thread_time() - start

    subscription.callback = timed_callback
    node.publisher.publish = timed_publish


def instrument_fuser(node, shared):
    """
    Count the fuser's input messages and time its callbacks and timers.

    The subscription callback copies the fuser's own ``messages_in`` counter to
    shared memory; ``fuse_queued`` adds the rows it fused (accepted and gated out)
    and the fusion lag: from the last (and the oldest) input taken before it to the
    end of the map update.
    """
    (topic, source), = node.sources.items()
    pending = {'first': None, 'last': None}
    subscription = next(s for s in node.subscriptions if s.topic_name == source.topic)
    callback = subscription.callback

    def timed_callback(msg):
        start = time.thread_time()
        try:
            callback(msg)
        finally:
            now = time.thread_time()
            shared[CALLBACK_S] += now - start
            shared[THREAD_S] = now
            shared[MESSAGES] = source.counts['messages_in']
            wall = time.monotonic()
            pending['last'] = wall
            if pending['first'] is None:
                pending['first'] = wall

    subscription.callback = timed_callback

    def fuse_wrapper(function):
        def timed():
            start = time.thread_time()
            first, last = pending['first'], pending['last']
            pending['first'] = None
            try:
                function()
            finally:
                now = time.thread_time()
                shared[FUSE_S] += now - start
                shared[THREAD_S] = now
                if first is not None:
                    end = time.monotonic()
                    shared[FUSE_CALLS] += 1
                    shared[ROWS_FUSED] = source.counts['fused'] + source.counts['gated_out']
                    shared[LAG_SUM] += end - last
                    shared[LAG_MAX] = max(shared[LAG_MAX], end - last)
                    shared[LAG_OLDEST_SUM] += end - first
                    shared[LAG_OLDEST_MAX] = max(shared[LAG_OLDEST_MAX], end - first)
        return timed

    def other_wrapper(function, field):
        def timed():
            start = time.thread_time()
            try:
                function()
            finally:
                now = time.thread_time()
                shared[field] += now - start
                shared[THREAD_S] = now
        return timed

    for timer in node.timers:
        name = getattr(timer.callback, '__name__', '')
        if name == 'fuse_queued':
            timer.callback = fuse_wrapper(timer.callback)
        else:
            timer.callback = other_wrapper(timer.callback,
                                           MAP_PUB_S if name == 'publish_map' else OTHER_S)


def fuser_parameters(fusion, input_depth):
    """Return the fuser's parameter overrides: fusion method and input depth."""
    return [Parameter('fusion', value=fusion), Parameter('input_depth', value=input_depth)]


def peak_rss_kb():
    """
    Return this process's peak RSS [kB]: ``VmHWM`` and ``getrusage`` ``ru_maxrss``.

    Linux keeps ``ru_maxrss`` across ``exec``, so in a spawned process it is at least
    the parent's RSS when it was spawned; ``VmHWM`` is the process's own peak.
    """
    return _common.vm_hwm_kb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def serve(kind, domain_id, input_depth, records, shared, conn):
    """
    Run one node under test until ``shared[STOP]`` is set (process entry point).

    Sends ``('ready', pid)`` once spinning, then ``('done', stats)`` with the node's
    counters and the process's peak RSS; failures send ``('error', text)``. The
    node logs errors only (its throttled warnings about gated-out rows would clutter
    the report; the counters have them).
    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = executor = None
    try:
        namespace = NAMESPACES[kind]
        if kind == 'relay':
            node = _common.relay('landmarks', input_qos(input_depth), 'relayed', QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=RELAY_OUTPUT_DEPTH,
                reliability=ReliabilityPolicy.RELIABLE), context=context, namespace=namespace)
            instrument_relay(node, shared)
        else:
            node = LandmarkFuser(context=context, namespace=namespace,
                                 parameter_overrides=fuser_parameters(kind, input_depth))
            node.map.load_records(records)
            instrument_fuser(node, shared)
        node.get_logger().set_level(LoggingSeverity.ERROR)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        shared[THREAD_S] = time.thread_time()
        conn.send(('ready', os.getpid()))
        while not shared[STOP]:
            executor.spin_once(timeout_sec=0.1)
        if kind == 'relay':
            stats = {'messages': node.count}
        else:
            stats = dict(node.counters.counts)
            for source in node.sources.values():
                stats.update({f'source_{k}': v for k, v in source.counts.items()})
            stats['landmarks'] = len(node.map)
        stats['hwm_kb'], stats['maxrss_kb'] = peak_rss_kb()
        conn.send(('done', stats))
    except Exception:  # reported to the driver, which prints it
        conn.send(('error', traceback.format_exc()))
    finally:
        _common.shutdown(executor, node, context, conn)


class Server(_common.Server):
    """A node under test in a spawned process, with its pipe and shared counters."""

    def __init__(self, mp_context, kind, domain_id, input_depth, records):
        self.shared = mp_context.RawArray('d', FIELDS)
        super().__init__(mp_context, kind, serve,
                         (kind, domain_id, input_depth, records, self.shared), duplex=False)

    def snapshot(self):
        """Return a copy of the shared counters."""
        return list(self.shared)

    def request_stop(self):
        """Set the stop flag in the shared counters."""
        self.shared[STOP] = 1.0
        return True


# --- The driver: no executor, an rcl wait set and serialized messages. -------------

def header(stamp_s):
    """Return a Header in the world frame at ``stamp_s`` seconds."""
    return make_header(stamp_s, WORLD_FRAME)


def landmark_payloads(truth, count, seed):
    """Return ``count`` serialized ``landmarks`` messages of ``ROWS_PER_MESSAGE`` rows."""
    pool = make_pool(truth, count * ROWS_PER_MESSAGE, seed)
    result = []
    for k in range(count):
        part = slice(k * ROWS_PER_MESSAGE, (k + 1) * ROWS_PER_MESSAGE)
        result.append(serialize_message(landmark_message(
            header(1000.0 + 0.01 * k), pool['ids'][part], pool['m'][part], pool['P'][part],
            pool['P_dep'][part])))
    return result


def probe_payload(landmark_id):
    """Return a serialized message of two agreeing rows of a new landmark."""
    m = np.array([[60.0 + landmark_id % 100, 60.0]] * 2)
    P = np.array([np.diag([0.04, 0.05])] * 2)
    return serialize_message(landmark_message(header(2000.0), [landmark_id] * 2, m, P,
                                              0.5 * P))


def make_target(node, kind, input_depth, window):
    """Return the driver's publisher and raw output subscription for one node under test."""
    namespace = NAMESPACES[kind]
    publisher = node.create_publisher(PointCloud2, f'/{namespace}/landmarks',
                                      input_qos(input_depth))
    if kind == 'relay':
        qos = input_qos(max(RELAY_OUTPUT_DEPTH, 2 * window))
        topic = f'/{namespace}/relayed'
    else:
        qos, topic = LATCHED, f'/{namespace}/fused_landmarks'
    subscription = node.create_subscription(PointCloud2, topic, lambda _: None, qos,
                                            raw=True)
    return _common.Target(node, kind, publisher, subscription)


def has_landmark(raw, landmark_id):
    """Return whether a serialized fused map holds ``landmark_id``."""
    return landmark_id in read_landmarks(deserialize_message(raw, PointCloud2)).ids


def run_window(target, server, payloads, window, warmup_s, measure_s, probe_id):
    """
    Keep ``window`` messages outstanding at one node; measure the messages it handles.

    Returns
    -------
    dict
        ``msg_per_s`` and ``rows_fused_per_s`` (counted in the node), ``node_cpu``
        and ``driver_cpu`` (processes, fractions of one core), ``thread_share``
        (executor thread CPU / wall), per message CPU of the executor thread
        [us]: ``cpu_us``, ``callback_us``, ``publish_us`` (relay), ``fuse_us``,
        ``map_pub_us``, ``other_us``; ``lag_ms``, ``lag_max_ms``,
        ``lag_oldest_ms``, ``lag_oldest_max_ms`` (in the fuser), ``e2e_lag_ms``
        (probe, fuser only), ``idle_polls`` (fraction of polls that found nothing
        outstanding), ``outputs`` (relay outputs / messages), ``lost``.

    """
    shared = server.shared
    state = {'sent': 0, 'base': shared[MESSAGES]}
    lost = polls = idle = outputs = 0

    def handled():
        return shared[MESSAGES] - state['base']

    def refill():
        while state['sent'] - handled() < window:
            target.publisher.publish(payloads[state['sent'] % len(payloads)])
            state['sent'] += 1

    start = time.perf_counter()
    measure_at, end_at = start + warmup_s, start + warmup_s + measure_s
    mark = None
    last_handled, last_progress = handled(), start
    refill()
    while True:
        now = time.perf_counter()
        if mark is None and now >= measure_at:
            shared[LAG_MAX] = shared[LAG_OLDEST_MAX] = 0.0
            mark = (now, server.snapshot(), _common.process_cpu_s(server.pid), time.process_time(),
                    outputs)
            polls = idle = 0
        if now >= end_at:
            break
        count, _ = target.wait(POLL_S)
        outputs += count if target.kind == 'relay' else 0
        done = handled()
        polls += 1
        idle += done >= state['sent']
        if done > last_handled:
            last_handled, last_progress = done, now
        elif now - last_progress > STALL_S:
            lost += state['sent'] - done
            state['sent'] = done
            last_progress = now
        refill()
    end = (time.perf_counter(), server.snapshot(), _common.process_cpu_s(server.pid),
           time.process_time(), outputs)
    e2e = float('nan')
    if probe_id is not None:
        # Sent behind a full window: it waits in the queue, then for both timers.
        target.publisher.publish(probe_payload(probe_id))
        state['sent'] += 1
        sent_at = time.perf_counter()
        deadline = sent_at + 2.0
        while time.perf_counter() < deadline:
            count, raw = target.wait(0.01)
            if count and has_landmark(raw, probe_id):
                e2e = time.perf_counter() - sent_at
                break
    # Let the node catch up so that the next run starts clean.
    deadline = time.perf_counter() + 2.0
    while handled() < state['sent'] and time.perf_counter() < deadline:
        target.wait(0.01)
    lost += max(state['sent'] - handled(), 0)
    wall = end[0] - mark[0]
    first, last = mark[1], end[1]

    def delta(field):
        return last[field] - first[field]

    messages = max(delta(MESSAGES), 1)
    fusions = max(delta(FUSE_CALLS), 1)
    per_message = {name: delta(field) / messages * 1e6 for name, field in (
        ('cpu_us', THREAD_S), ('callback_us', CALLBACK_S), ('publish_us', PUBLISH_S),
        ('fuse_us', FUSE_S), ('map_pub_us', MAP_PUB_S), ('other_us', OTHER_S))}
    return {
        'msg_per_s': delta(MESSAGES) / wall,
        'rows_fused_per_s': delta(ROWS_FUSED) / wall,
        'rows_per_fusion': delta(ROWS_FUSED) / fusions,
        'node_cpu': (end[2] - mark[2]) / wall,
        'driver_cpu': (end[3] - mark[3]) / wall,
        'thread_share': delta(THREAD_S) / wall,
        **per_message,
        'lag_ms': delta(LAG_SUM) / fusions * 1e3,
        'lag_max_ms': last[LAG_MAX] * 1e3,
        'lag_oldest_ms': delta(LAG_OLDEST_SUM) / fusions * 1e3,
        'lag_oldest_max_ms': last[LAG_OLDEST_MAX] * 1e3,
        'e2e_lag_ms': e2e * 1e3,
        'idle_polls': idle / max(polls, 1),
        'outputs': (end[4] - mark[4]) / messages,
        'lost': lost,
    }


def start_servers(args, domain_id, records):
    """Start the three nodes under test; return them once they spin."""
    mp_context = multiprocessing.get_context('spawn')
    servers = {}
    try:
        for kind in KINDS:
            servers[kind] = Server(mp_context, kind, domain_id, args.input_depth,
                                   records.get(kind))
        for server in servers.values():
            server.wait_ready(60.0)
    except BaseException:
        stop_servers(servers)
        raise
    return servers


def stop_servers(servers):
    """Stop the nodes under test; return their final statistics (kind -> dict)."""
    for server in servers.values():
        server.stop()
    return {kind: server.stats or {} for kind, server in servers.items()}


def node_rates(args, servers, domain_id, truth, deadline_s):
    """
    Feed the three nodes in turn and measure them.

    Returns
    -------
    dict
        ``kind -> list of run_window results``.

    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = None
    runs = {kind: [] for kind in KINDS}
    try:
        payloads = landmark_payloads(truth, POOL_MESSAGES, args.seed + 2)
        node = rclpy.create_node('bench_fuser_driver', context=context)
        targets = {kind: make_target(node, kind, args.input_depth, args.window)
                   for kind in KINDS}
        pairs = [(t.publisher, t.subscription) for t in targets.values()]
        if not _common.wait_for_match(pairs, 20.0):
            raise RuntimeError('driver and nodes did not match within 20 s')
        probe_id = PROBE_ID0
        for rep in range(args.reps):
            for kind in (KINDS if rep % 2 == 0 else KINDS[::-1]):
                probe = None if kind == 'relay' else probe_id
                probe_id += kind != 'relay'
                runs[kind].append(run_window(targets[kind], servers[kind], payloads,
                                             args.window, args.warmup, args.measure, probe))
            if time.perf_counter() > deadline_s and 2 <= rep + 1 < args.reps:
                print(f'(time budget reached after {rep + 1} rounds)')
                break
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    return runs


# --- Part 3: the fuser's own processing, in-process. --------------------------------

def own_processing(args, domain_id, records, truth):
    """
    Time and profile the fuser's callback and ``fuse_queued``, without executor.

    Returns
    -------
    dict
        ``method -> {'callback_us', 'fuse_us', 'profile'}``: times per message (best
        of 3 blocks) and the cProfile (entries, total_ms per message).

    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    messages = [deserialize_message(p, PointCloud2)
                for p in landmark_payloads(truth, 200, args.seed + 3)]
    per = args.fuse_every
    result = {}
    try:
        for method in ('split_covariance_intersection', 'independent'):
            node = LandmarkFuser(context=context, namespace=f'bench_inproc_{SHORT[method]}',
                                 parameter_overrides=fuser_parameters(method, args.input_depth))
            node.get_logger().set_level(LoggingSeverity.ERROR)
            try:
                node.map.load_records(records[method])
                (topic, _), = node.sources.items()
                blocks = []
                for block in range(4):
                    callback_s = fuse_s = 0.0
                    for k in range(0, len(messages), per):
                        start = time.perf_counter()
                        for msg in messages[k:k + per]:
                            node.on_landmarks(msg, topic)
                        middle = time.perf_counter()
                        node.fuse_queued()
                        callback_s += middle - start
                        fuse_s += time.perf_counter() - middle
                    if block:  # the first block is a warm-up
                        blocks.append((callback_s / len(messages) * 1e6,
                                       fuse_s / len(messages) * 1e6))
                best = min(blocks, key=sum)

                def step(i, node=node, topic=topic):
                    for msg in messages[(i * per) % len(messages):][:per]:
                        node.on_landmarks(msg, topic)
                    node.fuse_queued()

                entries, total = profile_calls(step, len(messages) // per, args.top)
                result[method] = {
                    'callback_us': best[0], 'fuse_us': best[1],
                    'profile': ([(w, tt / per, ct / per, nc / per) for w, tt, ct, nc in entries],
                                total / per)}
            finally:
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return result


# --- Report. ------------------------------------------------------------------------

def _median(runs, key):
    return _common.median_of(runs, key, skip_nan=True)


def _spread(values, fmt):
    return f'{fmt.format(min(values))}-{fmt.format(max(values))}' if values else '-'


def _mb(kb):
    return f'{kb / 1024:.0f} MB' if kb else '?'


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
        ``core`` (see ``core_fusion``), ``rates`` (kind -> median msg/s), ``ratio``
        (fusion -> fuser / relay), ``targets`` (name -> bool), ``seconds``.

    """
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--reps', type=int, default=3,
                        help='rounds of relay/fuser runs (default 3)')
    parser.add_argument('--window', type=int, default=50,
                        help='messages outstanding per node (default 50)')
    parser.add_argument('--warmup', type=float, default=0.3,
                        help='seconds of each run before measuring (default 0.3)')
    parser.add_argument('--measure', type=float, default=1.0,
                        help='measured seconds of each run (default 1.0)')
    parser.add_argument('--input-depth', type=int, default=FuserConfig().input_depth,
                        help='input queue depth of the nodes (default: the fuser default)')
    parser.add_argument('--min-seconds', type=float, default=0.25,
                        help='least time spent timing each method and batch size '
                        '(default 0.25)')
    parser.add_argument('--max-seconds', type=float, default=1.2,
                        help='no further calls of a method and batch size once this much '
                        'time is spent on it (default 1.2)')
    parser.add_argument('--pool-rows', type=int, default=400_000,
                        help='distinct observation rows of the core part (default 400000)')
    parser.add_argument('--loop-n', type=int, default=1000,
                        help='rows of the textbook loop (default 1000)')
    parser.add_argument('--fuse-every', type=int, default=20,
                        help='messages per fuse_queued in the in-process part (default 20)')
    parser.add_argument('--top', type=int, default=10,
                        help='functions shown from each profile (default 10)')
    parser.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS domain ID, 0-232 (default 201-214 from the PID); the '
                        'in-process part uses the next one')
    parser.add_argument('--budget', type=float, default=55.0,
                        help='stop starting new rounds after this many seconds (default 55)')
    args = parser.parse_args(argv)
    if args.window >= args.input_depth:
        parser.error('--window must be below --input-depth, or keep-last drops messages')
    if args.pool_rows < max(BATCHES) + args.loop_n:
        parser.error(f'--pool-rows must be at least {max(BATCHES) + args.loop_n}')
    # 201-214: clear of the tests' range (1-200) and of bench_observer's (215-232).
    domain_id = args.domain if args.domain is not None else 201 + os.getpid() % 13
    started = time.perf_counter()
    host = _common.machine()
    load_start = os.getloadavg()[0]

    truth = make_world(args.seed)
    maps, warm_rate = {}, {}
    for method in FUSION_METHODS:
        maps[method], warm_rate[method] = warm_map(method, truth, args.seed + 10)
    records = {kind: maps[kind].to_records() for kind in KINDS if kind in maps}
    # The node processes start before the core part: they are spawned from a small
    # process, and their start-up does not compete with the timed core calls.
    servers = start_servers(args, domain_id, records)
    try:
        core_started = time.perf_counter()
        core = core_fusion(args, truth, maps)
        core_s = time.perf_counter() - core_started
        runs = node_rates(args, servers, domain_id, truth, started + args.budget - 10.0)
    finally:
        stats = stop_servers(servers)
    own = own_processing(args, domain_id + 1, records, truth)
    seconds = time.perf_counter() - started
    load_end = os.getloadavg()[0]
    driver_rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    cells, loop = core['cells'], core['loop']
    best_batch = {m: max(BATCHES, key=lambda b, m=m: cells[m, b]['best'])
                  for m in FUSION_METHODS}
    best_rate = {m: cells[m, best_batch[m]]['best'] for m in FUSION_METHODS}
    loop_ratio = {m: best_rate[m] / loop[m]['obs_per_s'] for m in FUSION_METHODS}
    fusers = [k for k in KINDS if k != 'relay']
    rates = {kind: _median(runs[kind], 'msg_per_s') for kind in KINDS}
    ratio = {kind: statistics.median(f['msg_per_s'] / r['msg_per_s']
                                     for r, f in zip(runs['relay'], runs[kind]))
             for kind in fusers}
    cpu_ratio = {kind: _median(runs['relay'], 'cpu_us') / _median(runs[kind], 'cpu_us')
                 for kind in fusers}
    lost = int(sum(run['lost'] for kind in KINDS for run in runs[kind]))
    targets = {
        'core_independent': best_rate['independent'] >= TARGET_OBS_PER_S,
        **{f'node_{SHORT[k]}': ratio[k] >= TARGET_RATIO for k in fusers},
    }
    loop_agree = all(loop[m]['max_abs_diff'] <= AGREEMENT_ATOL for m in MUST_MATCH)
    cpu_batch = max(BATCHES, key=lambda b: cells['independent', b]['cpu'])
    cpu_best = cells['independent', cpu_batch]['cpu']
    rounds = len(runs['relay'])

    lines = [
        f'bench_fuser: LandmarkMap.update and landmark_fuser, {LANDMARKS} confirmed '
        f'landmarks, seed {args.seed}',
        _common.machine_line(host, domain_id, load_start, load_end),
        '',
        'core fusion: LandmarkMap.update on batches of random IDs into the warmed map, '
        'obs/s best / median / worst of the calls (per-row sources and stamps, as the '
        'node calls it)',
        '(CPU obs/s: median over the calls of rows / CPU time of the thread, which other '
        'load does not inflate)',
        'method                        |  batch | calls |    best obs/s |  median obs/s |'
        '   worst obs/s |  CPU obs/s | gated out',
    ]
    for method in FUSION_METHODS:
        for batch in BATCHES:
            cell = cells[method, batch]
            lines.append(f'{method:29s} | {batch:6d} | {cell["calls"]:5d} | '
                         f'{cell["best"]:13.4g} | {cell["median"]:13.4g} | '
                         f'{cell["worst"]:13.4g} | {cell["cpu"]:10.4g} | '
                         f'{cell["gated_out"] * 100:6.2f} %')
    lines.append(f'textbook loop (dict lookup, gate, gaussian.* on one 2-vector and 2x2 '
                 f'matrices per row), {args.loop_n} rows, best of up to 5 (0.6 s); ratio = '
                 'best batch / loop; max |diff| of means and covariances, loop vs one update '
                 'of the same rows:')
    for method in FUSION_METHODS:
        diff = loop[method]['max_abs_diff']
        match = ('match' if diff <= AGREEMENT_ATOL else 'DIFFER') if method in MUST_MATCH \
            else ('match' if diff <= AGREEMENT_ATOL else 'differ: not per-observation')
        lines.append(f'  {method:29s} loop {loop[method]["obs_per_s"]:9.4g} obs/s  best '
                     f'{best_rate[method]:9.4g} obs/s at {best_batch[method]:6d} rows  '
                     f'ratio {loop_ratio[method]:6.1f}x  max |diff| {diff:.1e} {match}')
    lines.append('warm-up (new landmarks, tentative path, 2 rows per ID): ' + ', '.join(
        f'{m} {warm_rate[m]:.3g} obs/s' for m in FUSION_METHODS))
    batch, calls, entries, total = core['profile']
    lines.append(f'cProfile of update, independent, {batch} rows, {calls} calls '
                 f'({total:.2f} ms/call under the profiler); tottime ms/call, cumtime '
                 'ms/call, calls/call, function:')
    for where, tottime, cumtime, ncalls in entries:
        lines.append(f'  {tottime:8.3f} {cumtime:8.3f} {ncalls:7.1f}  {where}')
    lines += [
        f'core target: independent >= {TARGET_OBS_PER_S:.3g} obs/s at its best batch size '
        f'({best_batch["independent"]} rows, {best_rate["independent"]:.4g} obs/s): '
        f'{_common.verdict(targets["core_independent"])} (by CPU time: {cpu_best:.4g} obs/s at '
        f'{cpu_batch} rows)',
        '',
        f'node: messages handled per second at {ROWS_PER_MESSAGE} rows/message, counted '
        f'in the node; closed loop, window {args.window}, input depth {args.input_depth} '
        f'(reliable), {rounds} rounds of {args.warmup:g} s warm-up + {args.measure:g} s '
        '(medians; spread = min-max of the rounds)',
        'node              |  msg/s | spread      | ratio | rows fused/s | CPU node / '
        'driver | thread share | idle polls',
    ]
    for kind in KINDS:
        values = [run['msg_per_s'] for run in runs[kind]]
        ratio_text = ' 1.00' if kind == 'relay' else f'{ratio[kind]:5.2f}'
        fused = '-' if kind == 'relay' else f'{_median(runs[kind], "rows_fused_per_s"):.0f}'
        lines.append(f'{LABELS[kind]:17s} | {rates[kind]:6.0f} | '
                     f'{_spread(values, "{:.0f}"):11s} | {ratio_text} | {fused:>12s} | '
                     f'{_median(runs[kind], "node_cpu") * 100:4.0f} % / '
                     f'{_median(runs[kind], "driver_cpu") * 100:3.0f} %  | '
                     f'{_median(runs[kind], "thread_share") * 100:10.0f} % | '
                     f'{_median(runs[kind], "idle_polls") * 100:5.1f} %')
    lines += [
        'each round (msg/s, relay / split CI / independent): ' + '; '.join(
            '/'.join(f'{runs[k][i]["msg_per_s"]:.0f}' for k in KINDS) for i in range(rounds)),
        '',
        "per message, CPU time of the node's executor thread [us] (robust to other load): "
        'callback = input callback (relay: publish included), fusion = fuse_queued timer, '
        'map pub = publish_map timer, other = diagnostics timer, executor = the rest '
        '(wait set, take, deserialize)',
        'node              |  total | callback | publish | fusion | map pub | other | '
        'executor',
    ]
    for kind in KINDS:
        total_us = _median(runs[kind], 'cpu_us')
        parts = {key: _median(runs[kind], key) for key in (
            'callback_us', 'publish_us', 'fuse_us', 'map_pub_us', 'other_us')}
        executor_us = total_us - sum(v for k, v in parts.items() if k != 'publish_us')
        lines.append(f'{LABELS[kind]:17s} | {total_us:6.0f} | {parts["callback_us"]:8.0f} | '
                     f'{parts["publish_us"]:7.0f} | {parts["fuse_us"]:6.0f} | '
                     f'{parts["map_pub_us"]:7.1f} | {parts["other_us"]:5.1f} | '
                     f'{executor_us:8.0f}')
    lines.append('CPU-time ratio relay/fuser per message (what the msg/s ratio would be on '
                 'idle cores): ' + ', '.join(f'{LABELS[k]} {cpu_ratio[k]:.2f}'
                                             for k in fusers))
    lines.append('fusion lag in the fuser, last input -> map updated (mean / max) and oldest '
                 'input -> map updated (mean / max), rows per fusion; end to end (probe '
                 'behind a full window -> fused_landmarks holds it, median and spread):')
    for kind in fusers:
        e2e = [run['e2e_lag_ms'] for run in runs[kind] if not math.isnan(run['e2e_lag_ms'])]
        lines.append(f'  {LABELS[kind]:17s} {_median(runs[kind], "lag_ms"):6.1f} / '
                     f'{max(run["lag_max_ms"] for run in runs[kind]):6.1f} ms, '
                     f'{_median(runs[kind], "lag_oldest_ms"):6.1f} / '
                     f'{max(run["lag_oldest_max_ms"] for run in runs[kind]):6.1f} ms, '
                     f'{_median(runs[kind], "rows_per_fusion"):6.0f} rows; end to end '
                     f'{_median(runs[kind], "e2e_lag_ms"):6.0f} ms '
                     f'({_spread(e2e, "{:.0f}")}, {len(e2e)}/{len(runs[kind])} seen)')
    relay_outputs = _median(runs['relay'], 'outputs')
    lines.append(f'lost messages {lost}; relay outputs per handled message '
                 f'{relay_outputs:.3f}')
    for kind in fusers:
        counts = stats.get(kind) or {}
        problems = {k: v for k, v in counts.items() if v and not k.startswith('source_') and k
                    not in ('landmarks', 'maxrss_kb', 'hwm_kb', 'landmarks_confirmed')}
        lines.append(f'{LABELS[kind]} counters: {counts.get("source_messages_in")} messages '
                     f'in, {counts.get("source_fused")} rows fused, '
                     f'{counts.get("source_gated_out", 0)} gated out, '
                     f'{counts.get("landmarks")} landmarks; other counters '
                     f'{problems or "none"}')
    lines += [
        'peak memory, VmHWM of each node process (getrusage maxrss in brackets: Linux '
        "carries the spawning process's RSS over exec into it): " + ', '.join(
            f'{LABELS[k]} {_mb(stats[k].get("hwm_kb"))} ({_mb(stats[k].get("maxrss_kb"))})'
            for k in KINDS)
        + f'; this process (driver and core part, getrusage maxrss) {_mb(driver_rss_kb)}',
        '',
        f'fuser own processing, in-process without executor (callback on deserialized '
        f'{ROWS_PER_MESSAGE}-row messages, fuse_queued every {args.fuse_every}), per '
        'message, best of 3 blocks:',
    ]
    for method in ('split_covariance_intersection', 'independent'):
        lines.append(f'  {method:29s} callback {own[method]["callback_us"]:6.0f} us, '
                     f'fusion {own[method]["fuse_us"]:6.0f} us')
    for method in ('split_covariance_intersection', 'independent'):
        entries, total = own[method]['profile']
        lines.append(f'cProfile, {method} ({total * 1e3:.0f} us/msg under the profiler); '
                     'tottime us/msg, cumtime us/msg, calls/msg, function:')
        for where, tottime, cumtime, ncalls in entries:
            lines.append(f'  {tottime * 1e3:7.1f} {cumtime * 1e3:8.1f} {ncalls:5.2f}  {where}')
    lines += [
        '',
        f'targets: core independent >= {TARGET_OBS_PER_S:.3g} obs/s '
        f'({best_rate["independent"]:.3g}): {_common.verdict(targets["core_independent"])}; '
        + '; '.join(f'{LABELS[k]} msg/s >= {TARGET_RATIO:.0%} of relay ({ratio[k]:.2f}): '
                    f'{_common.verdict(targets[f"node_{SHORT[k]}"])}' for k in fusers)
        + f'; loop and update agree ({", ".join(SHORT[m] for m in MUST_MATCH)}): '
        f'{_common.verdict(loop_agree)}; run time {seconds:.1f} s (core part {core_s:.1f} s)',
        'RESULT bench_fuser'
        + ''.join(f' core_{SHORT[m]}_obs_per_s_{b}={cells[m, b]["best"]:.6g}'
                  for m in FUSION_METHODS for b in BATCHES)
        + f' core_independent_cpu_obs_per_s={cpu_best:.6g}'
        + ''.join(f' core_{SHORT[m]}_best_obs_per_s={best_rate[m]:.6g}'
                  f' core_{SHORT[m]}_best_batch={best_batch[m]}'
                  f' loop_{SHORT[m]}_obs_per_s={loop[m]["obs_per_s"]:.6g}'
                  f' loop_ratio_{SHORT[m]}={loop_ratio[m]:.4g}' for m in FUSION_METHODS)
        + f' relay_msg_per_s_{ROWS_PER_MESSAGE}={rates["relay"]:.6g}'
        + ''.join(f' fuser_{SHORT[k]}_msg_per_s_{ROWS_PER_MESSAGE}={rates[k]:.6g}'
                  f' ratio_{SHORT[k]}_{ROWS_PER_MESSAGE}={ratio[k]:.4g}'
                  f' cpu_ratio_{SHORT[k]}={cpu_ratio[k]:.4g}'
                  f' lag_{SHORT[k]}_ms={_median(runs[k], "lag_ms"):.4g}'
                  f' e2e_lag_{SHORT[k]}_ms={_median(runs[k], "e2e_lag_ms"):.4g}'
                  for k in fusers)
        + ''.join(f' peak_rss_{"relay" if k == "relay" else "fuser_" + SHORT[k]}_mb='
                  f'{(stats[k].get("hwm_kb") or 0) / 1024:.4g}' for k in KINDS)
        + f' maxrss_driver_mb={driver_rss_kb / 1024:.4g}'
        f' window={args.window} rounds={rounds} lost={lost} cpus={host["cpu_count"]}'
        f' pass={int(all(targets.values()) and loop_agree)}',
    ]
    print('\n'.join(lines))
    sys.stdout.flush()
    return {'core': core, 'rates': rates, 'ratio': ratio, 'targets': targets,
            'seconds': seconds}


if __name__ == '__main__':
    main()
    sys.exit(0)
