"""
Benchmark the observer: its pipeline object alone, then the node against a bare relay.

Part 1, pipeline level, in this process, no ROS: a ``observer.Observer`` with
the default parameters and 101 poses (100.00 s to 101.00 s every 10 ms) in its buffer.
Timed, per observation message of 1, 10 and 100 rows (stamps between poses, so every
message is interpolated and placed at once; every row valid):

- ``Observer.add_observations([message], now_ns)``: what the node calls per message
  (checks, pose lookup, placing);
- ``Observer.place([(message, pose, P_pose)])``: its placing step alone (noise ``R``,
  ``rows.landmarks_from_rows``: row checks, ``landmark_to_world_dependent``, result
  checks; the batches).

Best and median of blocks, garbage collector off. At 100 rows the public pieces are
also timed one by one on the same inputs (``PoseBuffer.lookup``, ``Observer.noise``,
``rows.row_problems``, ``core.landmarks.landmark_to_world_dependent``,
``rows.landmarks_from_rows``), and ``add_observations`` is profiled (cProfile): own
time by function and by package. Target: ``add_observations`` under 100 us per
100-row message.

Part 2, node level over DDS, side by side in one run. Two nodes under test, each in
its own process (``multiprocessing``, 'spawn') with its own ``SingleThreadedExecutor``,
both alive for the whole run, in their own namespaces of one private ROS domain:
``LandmarkObserver`` (namespace ``bench_observer``) and a relay (``bench_relay``) that
republishes every PointCloud2 from ``observations`` on ``landmarks`` unchanged, with
the observer's QoS (sensor-data input of depth ``input_depth``, reliable output of
depth ``output_depth``). Closed loop with a window, measured at the driver: the
driver keeps at most ``W`` (default 8, below the input depth, so best effort does not
drop in the queue) messages in flight per node and sends the next one when an output
arrives; rate = outputs per second over ``--measure`` s after ``--warmup`` s. The
driver has no executor (an rcl wait set, serialized messages in and out), so it stays
much cheaper than either node. Cost per message = CPU time of the node process (all
threads, ``/proc/<pid>/stat``) / outputs: nothing in the node is wrapped or patched,
and the figure does not count time spent waiting for a core. Relay and observer runs
alternate in each of ``--reps`` rounds at every size; tables give the medians, the
ratio the median of the per-round ratios. A message with no output for 0.25 s is
written off as lost.

Poses for part 2: 101 poses published in one burst on the observer's ``pose`` topic,
reliable with depth 1000 (the observer's pose subscription made so with its QoS
override parameters); the driver waits for the observer's ``/diagnostics`` to report
them in its buffer.

Targets are printed with PASS/FAIL; the script exits 0 whatever the result. The last
line is machine-readable::

    RESULT bench_observer key=value ...

Run from the repository root in the dev venv (``make bench``):
``python bench/bench_observer.py [--reps 4] [--window 8] [--measure 1.0]``.
"""

import argparse
import multiprocessing
import os
import statistics
import sys
import time
import traceback

# DDS discovery stays on this machine; set before rclpy is imported (the spawned node
# processes import this module too).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import _common  # noqa: E402
from landmark_ros.core.landmarks import landmark_to_world_dependent  # noqa: E402
from landmark_ros.observer import rows as observer_rows  # noqa: E402
from landmark_ros.observer.observer import ObservationMessage, Observer  # noqa: E402
from landmark_ros.pipeline.config import ObserverConfig  # noqa: E402
import numpy as np  # noqa: E402

ROWS = (1, 10, 100)
"""Rows per observation message."""

TARGET_RATIO = 0.8
"""Observer message rate at 100 rows, at least this fraction of the relay's."""

TARGET_OWN_US = 100.0
"""``Observer.add_observations`` per 100-row message [us]."""

RELAY_NS = 'bench_relay'
OBSERVER_NS = 'bench_observer'
KINDS = ('relay', 'observer')
NAMESPACES = {'relay': RELAY_NS, 'observer': OBSERVER_NS}

POSE_T0_NS = 100_000_000_000
POSE_STEP_NS = 10_000_000
POSE_COUNT = 101
POSE_DEPTH = 1000
P_POSE = np.array([[0.02, 0.005, 0.0], [0.005, 0.03, 0.001], [0.0, 0.001, 0.002]])
WORLD_FRAME = ObserverConfig().world_frame
SENSOR_FRAME = 'bench_sensor'
MESSAGES_PER_SIZE = 64
"""Distinct observation messages per size, sent in turn."""

STALL_S = 0.25
"""No output for this long with messages in flight: they are written off as lost."""

STOP = 0
"""Index of the stop flag in a node process's shared array."""


# --- Inputs, ROS-free. ------------------------------------------------------------

def poses():
    """Return the pose stream: ``(stamp_ns, pose)`` on a slow arc, every 10 ms."""
    result = []
    for k in range(POSE_COUNT):
        t = k * POSE_STEP_NS * 1e-9
        result.append((POSE_T0_NS + k * POSE_STEP_NS,
                       np.array([1.0 + t, 2.0 + 0.5 * t, 0.3 + 0.2 * t])))
    return result


def observations(rows, count=MESSAGES_PER_SIZE, seed=0):
    """
    Return ``count`` observation messages of ``rows`` rows: ``(stamp_ns, ids, z)``.

    Stamps lie strictly between the first and last pose stamps, off the pose grid, so
    each observation is interpolated; every row is valid.
    """
    rng = np.random.default_rng(seed + rows)
    span = (POSE_COUNT - 1) * POSE_STEP_NS
    result = []
    for i in range(count):
        stamp_ns = POSE_T0_NS + 3_700_000 + (span - 10_000_000) * i // count
        z = np.column_stack([rng.uniform(0.5, 30.0, rows), rng.uniform(-np.pi, np.pi, rows)])
        result.append((stamp_ns, rng.integers(0, 1000, rows).astype(np.int64), z))
    return result


def loaded_observer():
    """Return an ``Observer`` with the default parameters and the poses in its buffer."""
    observer = Observer(ObserverConfig())
    for stamp_ns, pose in poses():
        observer.add_pose(stamp_ns, pose, P_POSE, stamp_ns)
    if len(observer.poses) != POSE_COUNT:
        raise RuntimeError(f'pose buffer holds {len(observer.poses)} poses, '
                           f'expected {POSE_COUNT}')
    return observer


def observation_message(stamp_ns, ids, z):
    """Return the ``ObservationMessage`` the node makes of such a cloud (float64, int64)."""
    return ObservationMessage(stamp_ns, {'id': ids, 'range': z[:, 0].copy(),
                                         'bearing': z[:, 1].copy()}, SENSOR_FRAME)


# --- Part 1: the pipeline object. --------------------------------------------------

def pipeline(args):
    """
    Time ``Observer.add_observations`` and ``Observer.place``; break 100 rows down.

    Returns
    -------
    dict
        ``add`` and ``place`` (rows -> (best, median) of the blocks' CPU seconds per
        call, best wall seconds per call), ``counts_ok``, ``pieces`` (list of
        (label, best CPU seconds)), ``profile`` (``_common.profile_calls``).

    """
    observer = loaded_observer()
    now_ns = POSE_T0_NS + POSE_COUNT * POSE_STEP_NS
    result = {'add': {}, 'place': {}, 'counts_ok': True}
    messages = {}
    for rows in ROWS:
        messages[rows] = [observation_message(*item) for item in observations(rows)]
        batch = messages[rows]
        count = len(batch)
        before = observer.counters.counts['landmarks_out']
        calls = [0]

        def add(i, batch=batch, calls=calls):
            calls[0] += 1
            return observer.add_observations([batch[i % count]], now_ns)

        wall, cpu = _common.time_per_call(add, args.calls, args.blocks)
        result['add'][rows] = (min(cpu), statistics.median(cpu), min(wall))
        result['counts_ok'] &= (observer.counters.counts['landmarks_out'] - before
                                == calls[0] * rows) and not observer.pending
        ready = []
        for message in batch:
            found = observer.poses.lookup(message.stamp_ns)
            ready.append([(message, found.pose, found.P_pose)])
        wall, cpu = _common.time_per_call(
            lambda i, ready=ready: observer.place(ready[i % count]), args.calls, args.blocks)
        result['place'][rows] = (min(cpu), statistics.median(cpu), min(wall))
    big = messages[max(ROWS)]
    count = len(big)
    looked_up = [observer.poses.lookup(m.stamp_ns) for m in big]
    inputs = [(m.columns['id'], np.stack([m.columns['range'], m.columns['bearing']], axis=1),
               observer.noise(m.columns), found.pose, found.P_pose)
              for m, found in zip(big, looked_up)]
    pieces = [
        ('PoseBuffer.lookup (interpolation)',
         lambda i: observer.poses.lookup(big[i % count].stamp_ns)),
        ('Observer.noise', lambda i: observer.noise(big[i % count].columns)),
        ('rows.landmarks_from_rows (all below)',
         lambda i: observer_rows.landmarks_from_rows(*inputs[i % count])),
        ('  rows.row_problems',
         lambda i: observer_rows.row_problems(*inputs[i % count][:3])),
        ('  core landmark_to_world_dependent',
         lambda i: landmark_to_world_dependent(inputs[i % count][3], inputs[i % count][4],
                                               inputs[i % count][1], inputs[i % count][2])),
    ]
    result['pieces'] = [(label, min(_common.time_per_call(function, args.calls,
                                                          args.blocks)[1]))
                        for label, function in pieces]
    result['profile'] = _common.profile_calls(
        lambda i: observer.add_observations([big[i % count]], now_ns), args.profile_calls,
        args.top)
    return result


# --- Part 2: nodes under test, each in its own process. ----------------------------

def observer_overrides(namespace, input_depth):
    """Return the observer's parameters: input depth, reliable deep pose input."""
    from rclpy.parameter import Parameter
    topic = f'/{namespace}/pose'
    return [
        Parameter('input_depth', value=input_depth),
        Parameter(f'qos_overrides.{topic}.subscription.reliability', value='reliable'),
        Parameter(f'qos_overrides.{topic}.subscription.depth', value=POSE_DEPTH),
    ]


def serve(kind, domain_id, input_depth, shared, conn):
    """
    Run one node under test until ``shared[STOP]`` is set (process entry point).

    Sends ``('ready', pid)`` once spinning, then ``('done', stats)``: the observer's
    counters or the relay's count, and the process's peak RSS. Failures send
    ``('error', text)``.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from landmark_ros.nodes.observer import LandmarkObserver
    from landmark_ros.ros import qos
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = executor = None
    try:
        namespace = NAMESPACES[kind]
        if kind == 'observer':
            node = LandmarkObserver(context=context, namespace=namespace,
                                    parameter_overrides=observer_overrides(namespace,
                                                                           input_depth))
        else:
            node = _common.relay('observations', qos.sensor_input(input_depth), 'landmarks',
                                 qos.reliable_output(ObserverConfig().output_depth),
                                 context=context, namespace=namespace)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        conn.send(('ready', os.getpid()))
        while not shared[STOP]:
            executor.spin_once(timeout_sec=0.1)
        if kind == 'observer':
            stats = dict(node.counters.counts)
            stats['pose_buffer_size'] = len(node.observer.poses)
        else:
            stats = {'messages': node.count}
        stats['peak_rss_kb'] = _common.vm_hwm_kb()
        conn.send(('done', stats))
    except Exception:  # reported to the driver, which prints it
        conn.send(('error', traceback.format_exc()))
    finally:
        _common.shutdown(executor, node, context, conn)


class Server(_common.Server):
    """A node under test in a spawned process, with its pipe and stop flag."""

    def __init__(self, mp_context, kind, domain_id, input_depth):
        self.shared = mp_context.RawArray('d', 1)
        super().__init__(mp_context, kind, serve, (kind, domain_id, input_depth, self.shared),
                         duplex=False)

    def request_stop(self):
        """Set the stop flag."""
        self.shared[STOP] = 1.0
        return True


def make_target(node, kind, input_depth, window):
    """Return the driver's publisher and raw output subscription for one node under test."""
    from landmark_ros.ros import qos
    from sensor_msgs.msg import PointCloud2
    namespace = NAMESPACES[kind]
    publisher = node.create_publisher(PointCloud2, f'/{namespace}/observations',
                                      qos.sensor_input(input_depth))
    depth = max(ObserverConfig().output_depth, 2 * window)
    subscription = node.create_subscription(PointCloud2, f'/{namespace}/landmarks',
                                            lambda _: None, qos.reliable_output(depth),
                                            raw=True)
    return _common.Target(node, kind, publisher, subscription)


def send_poses(node, timeout):
    """
    Publish the pose stream to the observer; wait for its diagnostics to show them.

    Returns
    -------
    int or None
        The pose buffer size the observer reports, None if no report came.

    """
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from landmark_ros.ros.schemas import pose_message
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=POSE_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(PoseWithCovarianceStamped, f'/{OBSERVER_NS}/pose',
                                      reliable)
    diagnostics = node.create_subscription(DiagnosticArray, '/diagnostics', lambda _: None,
                                           10)
    try:
        if not _common.wait_for_match([(publisher, diagnostics)], timeout):
            return None
        for stamp_ns, pose in poses():
            publisher.publish(pose_message(stamp_ns * 1e-9, pose, P_POSE, WORLD_FRAME))
        deadline = time.monotonic() + timeout
        size = None
        wait_set = _common.wait_set_for(node)
        while time.monotonic() < deadline:
            for array in _common.take(wait_set, diagnostics, DiagnosticArray, False, 0.1):
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


def payloads(rows):
    """Return serialized ``observations`` clouds of ``rows`` rows each."""
    from landmark_ros.ros import schemas
    from rclpy.serialization import serialize_message
    return [serialize_message(schemas.observation_message(
        schemas.make_header(stamp_ns * 1e-9, SENSOR_FRAME), ids, z))
        for stamp_ns, ids, z in observations(rows)]


def run_window(target, messages, rows, server, window, warmup_s, measure_s):
    """
    Drive one node closed-loop with ``window`` messages in flight; measure outputs/s.

    Returns
    -------
    dict
        ``msg_per_s``; ``node_cpu`` and ``driver_cpu`` (fractions of one core);
        ``cpu_us`` (node process CPU time per output); ``lost`` (messages written
        off); ``outputs_ok`` (the last output has ``rows`` rows).

    """
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2
    state = {'sent': 0, 'in_flight': 0}

    def refill():
        while state['in_flight'] < window:
            target.publisher.publish(messages[state['sent'] % len(messages)])
            state['sent'] += 1
            state['in_flight'] += 1

    received = lost = 0
    last = mark = None
    start = time.perf_counter()
    measure_at, end_at = start + warmup_s, start + warmup_s + measure_s
    last_progress = start
    refill()
    while True:
        now = time.perf_counter()
        if mark is None and now >= measure_at:
            mark = (now, received, _common.process_cpu_s(server.pid), time.process_time())
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
    # Let the messages in flight come back so that the next run starts clean.
    deadline = time.perf_counter() + 1.0
    while state['in_flight'] > 0 and time.perf_counter() < deadline:
        count, _ = target.wait(0.01)
        state['in_flight'] -= count
    lost += max(state['in_flight'], 0)
    wall = end[0] - mark[0]
    outputs = max(end[1] - mark[1], 1)
    return {
        'msg_per_s': (end[1] - mark[1]) / wall,
        'node_cpu': (end[2] - mark[2]) / wall,
        'driver_cpu': (end[3] - mark[3]) / wall,
        'cpu_us': (end[2] - mark[2]) / outputs * 1e6,
        'lost': lost,
        'outputs_ok': last is not None and deserialize_message(last, PointCloud2).width == rows,
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
    import rclpy
    from rclpy.context import Context
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
        messages = {rows: payloads(rows) for rows in ROWS}
        for rep in range(args.reps):
            for rows in ROWS:
                for kind in (KINDS if rep % 2 == 0 else KINDS[::-1]):
                    runs[kind, rows].append(run_window(
                        targets[kind], messages[rows], rows, servers[kind], args.window,
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
        ``add_us`` and ``place_us`` (rows -> best us per message), ``throughput``
        ((kind, rows) -> median msg/s), ``ratio`` (rows -> observer / relay),
        ``targets`` (name -> bool) and ``seconds``.

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
    parser.add_argument('--calls', type=int, default=3000,
                        help='timed calls per pipeline case (default 3000)')
    parser.add_argument('--blocks', type=int, default=12,
                        help='blocks the timed calls are split into (default 12)')
    parser.add_argument('--profile-calls', type=int, default=1000,
                        help='calls under cProfile (default 1000)')
    parser.add_argument('--top', type=int, default=14,
                        help='functions shown from the profile (default 14)')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS domain ID of part 2, 0-232 (default 215-231 from the PID)')
    parser.add_argument('--budget', type=float, default=60.0,
                        help='stop starting new rounds after this many seconds (default 60)')
    parser.add_argument('--pipeline-only', action='store_true',
                        help='run part 1 only (no ROS)')
    args = parser.parse_args(argv)
    if args.window >= args.input_depth:
        parser.error('--window must be below --input-depth, or best effort drops messages')
    # 215-232 are free of the tests' range (1-200) and valid for the DDS port mapping.
    domain_id = args.domain if args.domain is not None else 215 + os.getpid() % 17
    started = time.perf_counter()
    host = _common.machine()

    own = pipeline(args)
    runs, info = ({}, {}) if args.pipeline_only else throughput(
        args, domain_id, started + args.budget - 15.0)
    seconds = time.perf_counter() - started
    big = max(ROWS)
    add_us = {rows: own['add'][rows][0] * 1e6 for rows in ROWS}
    place_us = {rows: own['place'][rows][0] * 1e6 for rows in ROWS}
    targets = {'add_us_100': add_us[big] < TARGET_OWN_US}

    lines = [
        'bench_observer: observer.Observer alone, then landmark_observer vs a bare '
        'relay node over DDS',
        _common.machine_line(host, None if args.pipeline_only else domain_id,
                             os.getloadavg()[0]),
        '',
        f'part 1, pipeline, no ROS: thread CPU us per message, best / median of '
        f'{args.blocks} blocks of {args.calls // args.blocks} calls, and best wall us '
        '(101 poses in the buffer, every message interpolated, every row valid)',
        'rows/msg | add_observations CPU (wall) | place CPU (wall)          | us/row (add)',
    ]
    for rows in ROWS:
        (a_best, a_med, a_wall), (p_best, p_med, p_wall) = own['add'][rows], own['place'][rows]
        lines.append(f'{rows:8d} | {a_best * 1e6:6.1f} / {a_med * 1e6:6.1f} '
                     f'({a_wall * 1e6:6.1f}) | '
                     f'{p_best * 1e6:6.1f} / {p_med * 1e6:6.1f} ({p_wall * 1e6:6.1f}) | '
                     f'{a_best * 1e6 / rows:8.2f}')
    lines.append(f'public pieces at {big} rows, called one by one on the same inputs '
                 '(thread CPU, best of the blocks):')
    for label, best in own['pieces']:
        lines.append(f'  {label:<40} {best * 1e6:7.1f} us')
    functions, packages, profiled_us, calls_per_call = own['profile']
    lines.append(f'cProfile of add_observations at {big} rows, {args.profile_calls} calls '
                 f'({profiled_us:.0f} us/msg under the profiler, {calls_per_call:.0f} function '
                 'calls/msg); own time by package:')
    lines.append('  ' + ', '.join(f'{name} {us:.1f} us' for name, us in packages[:8]))
    lines.append('  top functions by own time: tottime us/msg, cumtime us/msg, calls/msg, '
                 'function')
    for where, tottime, cumtime, ncalls in functions:
        lines.append(f'  {tottime:7.1f} {cumtime:8.1f} {ncalls:5.1f}  {where}')
    lines.append(f'target: add_observations at {big} rows < {TARGET_OWN_US:g} us CPU '
                 f'({add_us[big]:.1f} us): {_common.verdict(targets["add_us_100"])}; landmark '
                 f'counts {_common.verdict(own["counts_ok"])}')
    result = ('RESULT bench_observer'
              + ''.join(f' pipeline_add_us_{rows}={add_us[rows]:.4g}'
                        f' pipeline_place_us_{rows}={place_us[rows]:.4g}' for rows in ROWS))
    ratio = {}
    if runs:
        relay = {rows: _median(runs['relay', rows], 'msg_per_s') for rows in ROWS}
        observer = {rows: _median(runs['observer', rows], 'msg_per_s') for rows in ROWS}
        # Relay and observer runs of a round are next to each other in time: the median
        # of the per-round ratios cancels slow changes of the machine's load.
        ratio = {rows: statistics.median(o['msg_per_s'] / r['msg_per_s'] for r, o in zip(
            runs['relay', rows], runs['observer', rows])) for rows in ROWS}
        cpu = {(kind, rows): _median(runs[kind, rows], 'cpu_us') for kind in KINDS
               for rows in ROWS}
        cpu_ratio = {rows: cpu['relay', rows] / cpu['observer', rows] for rows in ROWS}
        targets['ratio_100'] = ratio[big] >= TARGET_RATIO
        lost = sum(run['lost'] for key in runs for run in runs[key])
        outputs_ok = all(run['outputs_ok'] for key in runs for run in runs[key])
        rounds = len(runs['relay', ROWS[0]])
        lines += [
            '',
            f'part 2, nodes over DDS: closed loop, window {args.window}, input depth '
            f'{args.input_depth}, {rounds} rounds of {args.warmup:g} s warm-up + '
            f'{args.measure:g} s per run; poses: {POSE_COUNT} sent, observer reported '
            f'{info.get("pose_buffer_size")} in its buffer',
            '(rates: medians of the rounds; ratio: median of the per-round ratios; CPU/msg: '
            'node process CPU time per output; CPU %: one core = 100 %)',
            'rows/msg | relay msg/s | observer msg/s | ratio | CPU/msg relay / observer | '
            'CPU-time ratio | CPU % relay / observer / driver',
        ]
        for rows in ROWS:
            lines.append(
                f'{rows:8d} | {relay[rows]:11.0f} | {observer[rows]:14.0f} | '
                f'{ratio[rows]:5.2f} | {cpu["relay", rows]:9.0f} / {cpu["observer", rows]:6.0f}'
                f' us | {cpu_ratio[rows]:14.2f} | '
                f'{_median(runs["relay", rows], "node_cpu") * 100:4.0f} / '
                f'{_median(runs["observer", rows], "node_cpu") * 100:4.0f} / '
                f'{_median(runs["observer", rows], "driver_cpu") * 100:4.0f}')
        lines.append('(CPU-time ratio relay/observer: what the msg/s ratio would be on idle '
                     'cores; observer CPU/msg - relay CPU/msg = what the node adds: decode, '
                     'pipeline, encode)')
        lines.append('each round (msg/s, relay / observer): ' + '; '.join(
            f'{rows} rows: ' + ', '.join(
                f'{r["msg_per_s"]:.0f}/{o["msg_per_s"]:.0f}'
                for r, o in zip(runs['relay', rows], runs['observer', rows]))
            for rows in ROWS))
        stats = info.get('observer_stats') or {}
        from landmark_ros.observer.observer import THROUGHPUT_COUNTERS
        problems = {k: v for k, v in stats.items() if v and k not in THROUGHPUT_COUNTERS
                    and k not in ('pose_buffer_size', 'peak_rss_kb')}
        lines.append(f'lost messages {lost}; outputs have the rows sent: '
                     f'{_common.verdict(outputs_ok)}; observer counters: '
                     f'{stats.get("observation_messages_in")} messages in, '
                     f'{stats.get("landmarks_out")} landmarks out, rejections '
                     f'{problems or "none"}')
        peak_mb = {kind: ((info.get(f'{kind}_stats') or {}).get('peak_rss_kb') or 0) / 1024
                   for kind in KINDS}
        lines.append('peak memory (VmHWM of the node processes): ' + ', '.join(
            f'{kind} {peak_mb[kind]:.0f} MB' for kind in KINDS))
        lines.append(f'target: observer msg/s at {big} rows >= {TARGET_RATIO:.0%} of relay '
                     f'({ratio[big]:.2f}): {_common.verdict(targets["ratio_100"])}')
        result += (''.join(f' relay_msg_per_s_{rows}={relay[rows]:.6g}'
                           f' observer_msg_per_s_{rows}={observer[rows]:.6g}'
                           f' ratio_{rows}={ratio[rows]:.4g}'
                           f' cpu_ratio_{rows}={cpu_ratio[rows]:.4g}' for rows in ROWS)
                   + f' observer_obs_per_s_{big}={observer[big] * big:.6g}'
                   f' relay_cpu_us_{big}={cpu["relay", big]:.4g}'
                   f' observer_cpu_us_{big}={cpu["observer", big]:.4g}'
                   + ''.join(f' peak_rss_{kind}_mb={peak_mb[kind]:.4g}' for kind in KINDS)
                   + f' window={args.window} rounds={rounds} lost={lost}')
    lines += ['', f'run time {seconds:.1f} s',
              result + f' cpus={host["cpu_count"]} pass={int(all(targets.values()))}']
    print('\n'.join(lines))
    sys.stdout.flush()
    return {'add_us': add_us, 'place_us': place_us, 'ratio': ratio, 'targets': targets,
            'seconds': seconds}


if __name__ == '__main__':
    main()
    sys.exit(0)
