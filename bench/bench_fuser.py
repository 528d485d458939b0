"""
Benchmark the fuser: its pipeline object alone, then the node against a bare relay.

Part 1, pipeline level, in this process, no ROS: for each fusion method a map is
warmed through a ``fuser.Fuser`` (source ``warmup``: 100-row messages with
two consistent observations of each of 1,000 landmarks, until all are confirmed) and
its records loaded into a ``Fuser`` with one other source, as the nodes of part 2
load them; that fuser is fed 100-row messages of random landmarks: timed per message,
``Fuser.add_landmark_messages`` (row checks, queue; ``max_batch_messages`` messages
per call, as the node takes them from its subscription) and ``Fuser.fuse_queued``
called every ``--fuse-every`` messages (about one ``update_period_s`` at the node's
rates), its time divided by the messages it fused. The observations are realistic and
consistent: a robot 2-20 m from the landmark, its pose estimate drawn from a full
3x3 pose covariance, range and bearing noise from a full 2x2 ``R``, placed with
``landmark_to_world_dependent`` (total covariance and dependent part). Thread CPU
time, best of blocks; then a cProfile of the same loop for the default method.
(``LandmarkMap.update`` throughput on big batches is ``bench_map.py``'s.)

Part 2, node level over DDS, side by side in one run. Six nodes under test, each
in its own process (``multiprocessing``, 'spawn') with its own
``SingleThreadedExecutor``, all alive for the whole run, in their own namespaces of
one private ROS domain: ``LandmarkFuser`` with ``split_covariance_intersection``
(the default), ``LandmarkFuser`` with ``independent``, and a bare relay
(subscribes PointCloud2 on ``landmarks`` and republishes it unchanged); then a
split-CI ``LandmarkFuser`` with 50 input topics (``input_topics`` ``landmarks_00`` to
``landmarks_49``: 50 sources) and a relay subscribed to the same 50 topics, the driver
publishing on the 50 topics in turn (one process for all the robots), every robot
seeing every landmark (the worst case for split CI, whose cost per row grows with a
landmark's sources); and a second such fuser fed by robots that each see their 100
nearest landmarks (robots at random places: about 5 robots per landmark). Each fuser is
compared with the relay on the same topics. The fusers' maps are loaded with the
warmed maps of part 1 (1,000 confirmed landmarks). Input QoS is the fuser's:
reliable, keep last, depth ``input_depth`` (100).

Nothing in the nodes is wrapped: each node process runs its executor with
``spin_once`` and, after each, copies public state into shared memory the driver
reads: the messages handled (the fuser's source counter ``messages_in``, the relay's
count) and, for the fusers, the fusion lag (from the spin that took the last input
before a fusion to the spin after which the queues are empty). The driver (this
process, no executor: pre-serialized 100-row ``landmarks`` messages) is the same for
all three: closed loop, it keeps ``W`` (default 50, below the input depth, so
reliable keep-last never overwrites) messages sent but not yet handled, polling
every 0.2 ms (a relay's outputs wake the driver at once, a fuser's are rare: at 1 ms
a fuser that had taken the whole window waited up to 1 ms for more, 25 % of the
polls found nothing outstanding); the node is the bottleneck (idle polls are
printed). Rate =
messages handled / wall time over ``--measure`` s after ``--warmup`` s; cost per
message = CPU time of the node process (all threads, ``/proc/<pid>/stat``) /
messages handled. The runs alternate in each of ``--reps`` rounds; tables give the
medians, the ratios the median of the per-round ratios. End-to-end lag: from the
driver publishing a probe (two rows of a new landmark, behind a full window) to the
first ``fused_landmarks`` holding it (queue, ``update_period_s`` and
``publish_rate_hz`` timers included).

Targets are printed with PASS/FAIL; the script exits 0 whatever the result. The last
line is machine-readable::

    RESULT bench_fuser key=value ...

Run from the repository root in the dev venv (``make bench``):
``python bench/bench_fuser.py [--reps 5] [--window 50] [--measure 1.0]``.
"""

import argparse
import math
import multiprocessing
import operator
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
from landmark_ros.fuser.fuser import Fuser, LandmarkMessage  # noqa: E402
from landmark_ros.fusion import compiled  # noqa: E402
from landmark_ros.fusion.landmark_map import FUSION_METHODS  # noqa: E402
from landmark_ros.nodes.fuser import LandmarkFuser  # noqa: E402
from landmark_ros.pipeline.config import FuserConfig  # noqa: E402
from landmark_ros.ros import qos  # noqa: E402
from landmark_ros.ros.schemas import landmark_message, make_header, read_landmarks  # noqa: E402
import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.logging import LoggingSeverity  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

LANDMARKS = 1000
"""Confirmed landmarks in the map."""

TARGET_RATIO = {'split_covariance_intersection': 0.8, 'independent': 0.8, 'split_many': 0.7,
                'split_local': 0.8}
"""Fuser message rate at 100 rows, at least this fraction of its relay's (the floors)."""

ROWS_PER_MESSAGE = 100
WORLD_FRAME = FuserConfig().world_frame
SOURCE = 'robot1'
"""The one source fed in the pipeline part."""
WARMUP_SOURCE = 'warmup'
"""The source that built the warmed maps."""
RELAY_OUTPUT_DEPTH = 10

MANY_SOURCES = 50
"""Input topics of the many-sources runs (one driver process publishing on all)."""

LOCAL_LANDMARKS = 100
"""Landmarks each robot of the local-fleet run sees: its nearest ones, so that a landmark
is seen by ``MANY_SOURCES * LOCAL_LANDMARKS / LANDMARKS`` (5) robots on average."""

KINDS = ('relay', 'split_covariance_intersection', 'independent', 'relay_many', 'split_many',
         'split_local')
"""Nodes under test: the relay and the fuser with two fusion methods on one input topic,
and a relay and two split-CI fusers on ``MANY_SOURCES`` input topics: every robot
seeing every landmark (the worst case), and each robot its ``LOCAL_LANDMARKS``
nearest landmarks (a fleet spread over the area)."""
RELAY_OF = {'split_covariance_intersection': 'relay', 'independent': 'relay',
            'split_many': 'relay_many', 'split_local': 'relay_many'}
"""Each fuser's reference relay (the same input topics)."""
FUSION_OF = {'split_covariance_intersection': 'split_covariance_intersection',
             'independent': 'independent', 'split_many': 'split_covariance_intersection',
             'split_local': 'split_covariance_intersection'}
NAMESPACES = {'relay': 'bench_relay', 'split_covariance_intersection': 'bench_fuser_sci',
              'independent': 'bench_fuser_ind', 'relay_many': 'bench_relay_many',
              'split_many': 'bench_fuser_sci_many', 'split_local': 'bench_fuser_sci_local'}
LABELS = {'relay': 'relay', 'split_covariance_intersection': 'fuser split CI',
          'independent': 'fuser independent', 'relay_many': f'relay {MANY_SOURCES} src',
          'split_many': f'split CI {MANY_SOURCES} src', 'split_local': 'split CI local'}
SHORT = {'split_covariance_intersection': 'split_ci', 'covariance_intersection': 'ci',
         'independent': 'independent', 'split_many': f'split_ci_{MANY_SOURCES}_sources',
         'split_local': f'split_ci_{MANY_SOURCES}_sources_local'}

POOL_MESSAGES = 400
"""Distinct messages fed in turn (pipeline part and driver)."""

POLL_S = 0.0002
"""Driver poll period [s] (see the module docstring)."""
STALL_S = 2.0
"""No message handled for this long with messages outstanding: written off as lost."""

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
    """Return ``n`` observation rows of random landmarks: ``ids``, ``m``, ``P``, ``P_dep``."""
    rng = np.random.default_rng(seed)
    ids = rng.integers(0, LANDMARKS, n)
    m, P, P_dep = observe(truth, ids, rng)
    return {'ids': ids, 'm': m, 'P': P, 'P_dep': P_dep}


def messages_of(pool):
    """Split a pool into 100-row messages: ``(stamp_ns, ids, m, P, P_dep)``."""
    result = []
    for k in range(len(pool['ids']) // ROWS_PER_MESSAGE):
        part = slice(k * ROWS_PER_MESSAGE, (k + 1) * ROWS_PER_MESSAGE)
        result.append((1_000_000_000_000 + k * 10_000_000, pool['ids'][part], pool['m'][part],
                       pool['P'][part], pool['P_dep'][part]))
    return result


def warm_fuser(fusion, truth, seed):
    """
    Return a ``Fuser`` whose map holds every landmark confirmed.

    Two observations per landmark (``min_observations``) in 100-row messages through
    ``add_landmarks`` and ``fuse_queued``; the rare landmark whose observations fail
    the gate gets more until it is confirmed.
    """
    rng = np.random.default_rng(seed)
    fuser = Fuser(FuserConfig(fusion=fusion), [WARMUP_SOURCE])
    ids = np.tile(np.arange(LANDMARKS), 2)
    for _ in range(10):
        m, P, P_dep = observe(truth, ids, rng)
        # Whole messages: the rows repeated up to a multiple of the message size.
        size = -(-len(ids) // ROWS_PER_MESSAGE) * ROWS_PER_MESSAGE
        pool = {key: np.resize(value, (size,) + value.shape[1:])
                for key, value in (('ids', ids), ('m', m), ('P', P), ('P_dep', P_dep))}
        for k, message in enumerate(messages_of(pool)):
            fuser.add_landmarks(WARMUP_SOURCE, LandmarkMessage(*message))
            if k % 20 == 19:
                fuser.fuse_queued()
        fuser.fuse_queued()
        confirmed = set(fuser.snapshot()[0].tolist())
        ids = np.array([i for i in range(LANDMARKS) if i not in confirmed], np.int64)
        if not len(ids):
            return fuser
    raise RuntimeError(f'{fusion}: {len(fuser.map)} landmarks confirmed by the warm-up, '
                       f'expected {LANDMARKS}')


# --- Part 1: the pipeline object. --------------------------------------------------


def time_blocks(warmed, messages, per, blocks):
    """
    Time a copy of ``warmed`` per message over ``blocks`` passes (after one warm-up).

    Returns ``add_us``, ``fuse_us`` (thread CPU time per message, the best pass) and
    ``gated_out`` (the fraction of rows gated out).
    """
    import copy
    timed = []
    for block in range(blocks + 1):
        fuser = copy.deepcopy(warmed)
        add_s = fuse_s = 0.0
        for k in range(0, len(messages), per):
            start = time.thread_time()
            add_bursts(fuser, messages[k:k + per])
            middle = time.thread_time()
            fuser.fuse_queued()
            add_s += middle - start
            fuse_s += time.thread_time() - middle
        if block:  # the first pass is a warm-up
            timed.append((add_s / len(messages), fuse_s / len(messages)))
    counts = fuser.sources[SOURCE].counts
    best = min(timed, key=sum)
    return {'add_us': best[0] * 1e6, 'fuse_us': best[1] * 1e6,
            'gated_out': counts['gated_out'] / max(counts['gated_out'] + counts['fused'], 1)}


def add_bursts(fuser, messages):
    """Queue ``messages`` as the node does: ``max_batch_messages`` per row check."""
    burst = FuserConfig().max_batch_messages
    for k in range(0, len(messages), burst):
        fuser.add_landmark_messages(SOURCE, [LandmarkMessage(*message)
                                             for message in messages[k:k + burst]])


def pipeline(args, truth):
    """
    Time ``Fuser.add_landmark_messages`` and ``Fuser.fuse_queued`` per message, each method.

    Returns
    -------
    dict
        ``method -> {'add_us', 'fuse_us', 'gated_out', 'records'}``: thread CPU time
        per message (best of the blocks), the fraction of rows gated out, and the
        warmed map's records (for the nodes); ``'profile'``: the cProfile of the
        default method (``_common.profile_calls``, per message).

    """
    import copy
    messages = messages_of(make_pool(truth, POOL_MESSAGES * ROWS_PER_MESSAGE, args.seed + 1))
    per = args.fuse_every
    result = {}
    compiled.load()
    for method in FUSION_METHODS:
        records = warm_fuser(method, truth, args.seed + 10).map.to_records()
        # Loaded from the records into a fuser fed by another source, as the nodes are.
        warmed = Fuser(FuserConfig(fusion=method), [SOURCE])
        warmed.map.load_records(records)
        result[method] = dict(time_blocks(warmed, messages, per, args.blocks),
                              records=records)
        if method == FuserConfig().fusion:
            # The same with change detection off (on by default: what it costs).
            plain = Fuser(FuserConfig(fusion=method, move_false_alarm_rate=0.0), [SOURCE])
            plain.map.load_records(records)
            result['no_detection'] = time_blocks(plain, messages, per, args.blocks)
            fuser = copy.deepcopy(warmed)

            def step(i, fuser=fuser):
                add_bursts(fuser, messages[(i * per) % len(messages):][:per])
                fuser.fuse_queued()

            functions, packages, total, calls = _common.profile_calls(
                step, len(messages) // per, args.top)
            result['profile'] = ([(w, tt / per, ct / per, nc / per)
                                  for w, tt, ct, nc in functions],
                                 [(name, us / per) for name, us in packages],
                                 total / per, calls / per)
    return result


# --- Part 2: nodes under test, each in its own process. ----------------------------

# Fields of the shared array a node process writes and the driver reads.
MESSAGES, FUSIONS, LAG_SUM, LAG_MAX, LAG_OLDEST_SUM, LAG_OLDEST_MAX, STOP = range(7)
FIELDS = 7


def input_topics(kind):
    """Return the input topics of a node under test (relative to its namespace)."""
    if kind in ('relay_many', 'split_many', 'split_local'):
        return [f'landmarks_{k:02d}' for k in range(MANY_SOURCES)]
    return ['landmarks']


QUEUE_MESSAGES = 100_000
"""``max_queue_messages`` of the fuser under test: at several thousand messages per
second from one source, the default 100 per source would drop the oldest messages
between fusions (a third of them at 8,000 msg/s and ``update_period_s`` 0.02 s), and
the fuser would be timed on the rows it did not fuse. No message may be dropped."""


def fuser_parameters(kind, input_depth):
    """Return the fuser's parameter overrides: fusion method, input topics and depth."""
    return [Parameter('fusion', value=FUSION_OF[kind]),
            Parameter('input_depth', value=input_depth),
            Parameter('input_topics', value=input_topics(kind)),
            Parameter('max_queue_messages', value=QUEUE_MESSAGES)]


def many_relay(topics, input_qos, output_topic, output_qos, **kwargs):
    """Return a relay node (``_common.relay``) that subscribes to every topic of ``topics``."""
    node = _common.relay(topics[0], input_qos, output_topic, output_qos, **kwargs)
    node.more = [node.create_subscription(PointCloud2, topic, node.on_message, input_qos)
                 for topic in topics[1:]]
    return node


def serve(kind, domain_id, input_depth, records, shared, conn):
    """
    Run one node under test until ``shared[STOP]`` is set (process entry point).

    After every ``spin_once`` the messages handled so far and, for a fuser, the lag
    of a fusion that just emptied the queues go to ``shared``. Sends ``('ready',
    pid)`` once spinning, then ``('done', stats)`` with the node's counters and the
    process's peak RSS; failures send ``('error', text)``. The fuser logs errors only
    (its throttled warnings about gated-out rows would clutter the report; the
    counters have them).
    """
    import resource
    if kind in RELAY_OF:
        compiled.load()     # time the fuser with its compiled fold (numba's disk cache)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = executor = None
    try:
        namespace = NAMESPACES[kind]
        if kind not in RELAY_OF:
            node = many_relay(input_topics(kind), qos.reliable_input(input_depth), 'relayed',
                              qos.reliable_output(RELAY_OUTPUT_DEPTH), context=context,
                              namespace=namespace)

            def handled():
                return node.count
        else:
            node = LandmarkFuser(context=context, namespace=namespace,
                                 parameter_overrides=fuser_parameters(kind, input_depth))
            node.fuser.map.load_records(records)
            sources = list(node.fuser.sources.values())
            # Read after every spin: C-level sums, so that the harness costs the fuser
            # with 50 sources about what it costs the relay (one attribute).
            # (The fuser clears its queues and counters in place.)
            counts = [source.counts for source in sources]
            queues = [source.queue for source in sources]
            in_count = operator.itemgetter('messages_in')

            def handled():
                return sum(map(in_count, counts))

            def queued():
                return sum(map(len, queues))
        node.get_logger().set_level(LoggingSeverity.ERROR)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        conn.send(('ready', os.getpid()))
        count, first, last = handled(), None, None
        while not shared[STOP]:
            executor.spin_once(timeout_sec=0.1)
            now = time.monotonic()
            if handled() != count:
                count = shared[MESSAGES] = handled()
                last = now
                first = now if first is None else first
            elif first is not None and not queued():
                shared[FUSIONS] += 1
                shared[LAG_SUM] += now - last
                shared[LAG_MAX] = max(shared[LAG_MAX], now - last)
                shared[LAG_OLDEST_SUM] += now - first
                shared[LAG_OLDEST_MAX] = max(shared[LAG_OLDEST_MAX], now - first)
                first = None
            if kind not in RELAY_OF:
                first = None
        if kind not in RELAY_OF:
            stats = {'messages': node.count}
        else:
            stats = dict(node.fuser.counters.counts)
            for source in sources:
                for k, v in source.counts.items():
                    stats[f'source_{k}'] = stats.get(f'source_{k}', 0) + v
            stats['landmarks'] = len(node.fuser.map)
        stats['hwm_kb'] = _common.vm_hwm_kb()
        stats['maxrss_kb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
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

def landmark_payloads(truth, count, seed):
    """Return ``count`` serialized ``landmarks`` messages of ``ROWS_PER_MESSAGE`` rows."""
    pool = make_pool(truth, count * ROWS_PER_MESSAGE, seed)
    result = []
    for k in range(count):
        part = slice(k * ROWS_PER_MESSAGE, (k + 1) * ROWS_PER_MESSAGE)
        result.append(serialize_message(landmark_message(
            make_header(1000.0 + 0.01 * k, WORLD_FRAME), pool['ids'][part], pool['m'][part],
            pool['P'][part], pool['P_dep'][part])))
    return result


def local_payloads(truth, count, seed):
    """
    Return ``count`` serialized messages, message ``k`` from robot ``k % MANY_SOURCES``.

    The robots stand at random places in the area; each sees its ``LOCAL_LANDMARKS``
    nearest landmarks, and its messages hold random rows of those. The driver sends
    message ``k`` on topic ``k % MANY_SOURCES`` (``count`` is a multiple of it).
    """
    rng = np.random.default_rng(seed)
    robots = rng.uniform(-50.0, 50.0, (MANY_SOURCES, 2))
    distance = np.linalg.norm(truth[None, :, :] - robots[:, None, :], axis=2)
    seen = np.argsort(distance, axis=1)[:, :LOCAL_LANDMARKS]
    result = []
    for k in range(count):
        ids = rng.choice(seen[k % MANY_SOURCES], ROWS_PER_MESSAGE)
        m, P, P_dep = observe(truth, ids, rng)
        result.append(serialize_message(landmark_message(
            make_header(1000.0 + 0.01 * k, WORLD_FRAME), ids, m, P, P_dep)))
    return result


def probe_payload(landmark_id):
    """Return a serialized message of two agreeing rows of a new landmark."""
    m = np.array([[60.0 + landmark_id % 100, 60.0]] * 2)
    P = np.array([np.diag([0.04, 0.05])] * 2)
    return serialize_message(landmark_message(make_header(2000.0, WORLD_FRAME),
                                              [landmark_id] * 2, m, P, 0.5 * P))


class RoundRobin:
    """Publishers used in turn, one message each (the many-sources runs)."""

    def __init__(self, publishers):
        self.publishers = publishers
        self.sent = 0

    def publish(self, payload, index=None):
        """Publish on publisher ``index`` (modulo their number), else on the next one."""
        turn = self.sent if index is None else index
        self.publishers[turn % len(self.publishers)].publish(payload)
        self.sent += 1

    def get_subscription_count(self):
        """Return the fewest subscriptions any of the publishers has."""
        return min(p.get_subscription_count() for p in self.publishers)


def make_target(node, kind, input_depth, window):
    """Return the driver's publisher(s) and raw output subscription for one node under test."""
    namespace = NAMESPACES[kind]
    publisher = RoundRobin([node.create_publisher(PointCloud2, f'/{namespace}/{topic}',
                                                  qos.reliable_input(input_depth))
                            for topic in input_topics(kind)])
    if kind not in RELAY_OF:
        subscription_qos = qos.reliable_input(max(RELAY_OUTPUT_DEPTH, 2 * window))
        topic = f'/{namespace}/relayed'
    else:
        subscription_qos, topic = qos.LATCHED, f'/{namespace}/fused_landmarks'
    subscription = node.create_subscription(PointCloud2, topic, lambda _: None,
                                            subscription_qos, raw=True)
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
        ``msg_per_s`` (counted in the node), ``node_cpu`` and ``driver_cpu``
        (processes, fractions of one core), ``cpu_us`` (node process CPU time per
        message handled), ``lag_ms``, ``lag_max_ms``, ``lag_oldest_ms``,
        ``lag_oldest_max_ms`` (in the fuser), ``e2e_lag_ms`` (probe, fuser only),
        ``idle_polls`` (fraction of polls that found nothing outstanding), ``lost``.

    """
    shared = server.shared
    state = {'sent': 0, 'base': shared[MESSAGES]}
    lost = polls = idle = 0

    def handled():
        return shared[MESSAGES] - state['base']

    def refill():
        while state['sent'] - handled() < window:
            # Payload k always on topic k modulo the topics (``local_payloads``).
            index = state['sent'] % len(payloads)
            target.publisher.publish(payloads[index], index)
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
            mark = (now, server.snapshot(), _common.process_cpu_s(server.pid),
                    time.process_time())
            polls = idle = 0
        if now >= end_at:
            break
        target.wait(POLL_S)
        done = handled()
        polls += 1
        idle += done >= state['sent']
        if done > last_handled:
            last_handled, last_progress = done, now
        elif now - last_progress > STALL_S:
            lost += state['sent'] - done
            state['sent'] = int(done)
            last_progress = now
        refill()
    end = (time.perf_counter(), server.snapshot(), _common.process_cpu_s(server.pid),
           time.process_time())
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
    fusions = max(delta(FUSIONS), 1)
    return {
        'msg_per_s': delta(MESSAGES) / wall,
        'node_cpu': (end[2] - mark[2]) / wall,
        'driver_cpu': (end[3] - mark[3]) / wall,
        'cpu_us': (end[2] - mark[2]) / messages * 1e6,
        'lag_ms': delta(LAG_SUM) / fusions * 1e3,
        'lag_max_ms': last[LAG_MAX] * 1e3,
        'lag_oldest_ms': delta(LAG_OLDEST_SUM) / fusions * 1e3,
        'lag_oldest_max_ms': last[LAG_OLDEST_MAX] * 1e3,
        'messages_per_fusion': messages / fusions,
        'e2e_lag_ms': e2e * 1e3,
        'idle_polls': idle / max(polls, 1),
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
        local = local_payloads(truth, POOL_MESSAGES, args.seed + 3)
        node = rclpy.create_node('bench_fuser_driver', context=context)
        targets = {kind: make_target(node, kind, args.input_depth, args.window)
                   for kind in KINDS}
        pairs = [(t.publisher, t.subscription) for t in targets.values()]
        if not _common.wait_for_match(pairs, 20.0):
            raise RuntimeError('driver and nodes did not match within 20 s')
        probe_id = PROBE_ID0
        for rep in range(args.reps):
            for kind in (KINDS if rep % 2 == 0 else KINDS[::-1]):
                probe = None if kind not in RELAY_OF else probe_id
                probe_id += kind in RELAY_OF
                runs[kind].append(run_window(targets[kind], servers[kind],
                                             local if kind == 'split_local' else payloads,
                                             args.window, args.warmup, args.measure, probe))
            if time.perf_counter() > deadline_s and 2 <= rep + 1 < args.reps:
                print(f'(time budget reached after {rep + 1} rounds)')
                break
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    return runs


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
        ``pipeline`` (see ``pipeline``), ``rates`` (kind -> median msg/s), ``ratio``
        (fusion -> fuser / relay), ``targets`` (name -> bool), ``seconds``.

    """
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--reps', type=int, default=5,
                        help='rounds of relay/fuser runs (default 5)')
    parser.add_argument('--window', type=int, default=50,
                        help='messages outstanding per node (default 50)')
    parser.add_argument('--warmup', type=float, default=0.3,
                        help='seconds of each run before measuring (default 0.3)')
    parser.add_argument('--measure', type=float, default=1.0,
                        help='measured seconds of each run (default 1.0)')
    parser.add_argument('--input-depth', type=int, default=FuserConfig().input_depth,
                        help='input queue depth of the nodes (default: the fuser default)')
    parser.add_argument('--fuse-every', type=int, default=20,
                        help='messages per fuse_queued in the pipeline part (default 20)')
    parser.add_argument('--blocks', type=int, default=3,
                        help='timed passes over the messages per method (default 3)')
    parser.add_argument('--top', type=int, default=10,
                        help='functions shown from the profile (default 10)')
    parser.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS domain ID, 0-232 (default 201-214 from the PID)')
    parser.add_argument('--budget', type=float, default=60.0,
                        help='stop starting new rounds after this many seconds (default 60)')
    parser.add_argument('--pipeline-only', action='store_true',
                        help='run part 1 only (no DDS)')
    args = parser.parse_args(argv)
    if args.window >= args.input_depth:
        parser.error('--window must be below --input-depth, or keep-last drops messages')
    # 201-214: clear of the tests' range (1-200) and of bench_observer's (215-232).
    domain_id = args.domain if args.domain is not None else 201 + os.getpid() % 13
    started = time.perf_counter()
    host = _common.machine()
    truth = make_world(args.seed)
    own = pipeline(args, truth)
    lines = [
        f'bench_fuser: fuser.Fuser alone, then landmark_fuser vs a bare relay node '
        f'over DDS; {LANDMARKS} confirmed landmarks, seed {args.seed}',
        '',
        f'part 1, pipeline, no ROS: thread CPU us per {ROWS_PER_MESSAGE}-row message, best '
        f'of {args.blocks} passes over {POOL_MESSAGES} messages; fuse_queued every '
        f'{args.fuse_every} messages, divided by the messages it fused',
        'method                        | add (burst)   | fuse_queued | total | gated out',
    ]
    for method in FUSION_METHODS:
        cell = own[method]
        lines.append(f'{method:29s} | {cell["add_us"]:13.1f} | {cell["fuse_us"]:11.1f} | '
                     f'{cell["add_us"] + cell["fuse_us"]:5.0f} | {cell["gated_out"] * 100:6.2f} %')
    cell, default = own['no_detection'], own[FuserConfig().fusion]
    total = cell['add_us'] + cell['fuse_us']
    lines.append(f'{"  - change detection":29s} | {cell["add_us"]:13.1f} | '
                 f'{cell["fuse_us"]:11.1f} | {total:5.0f} | {cell["gated_out"] * 100:6.2f} % '
                 f'({FuserConfig().fusion} with it, the default '
                 f'(move_false_alarm_rate {FuserConfig().move_false_alarm_rate:g}): '
                 f'{(default["add_us"] + default["fuse_us"]) / total:.2f}x this; no target)')
    functions, packages, total, calls = own['profile']
    lines.append(f'cProfile, {FuserConfig().fusion}, per message ({total:.0f} us under the '
                 f'profiler, {calls:.0f} function calls); own time by package:')
    lines.append('  ' + ', '.join(f'{name} {us:.1f} us' for name, us in packages[:8]))
    lines.append('  top functions by own time: tottime us/msg, cumtime us/msg, calls/msg, '
                 'function')
    for where, tottime, cumtime, ncalls in functions:
        lines.append(f'  {tottime:7.1f} {cumtime:8.1f} {ncalls:5.2f}  {where}')
    result = 'RESULT bench_fuser' + ''.join(
        f' pipeline_{SHORT[m]}_add_us={own[m]["add_us"]:.4g}'
        f' pipeline_{SHORT[m]}_fuse_us={own[m]["fuse_us"]:.4g}' for m in FUSION_METHODS) + (
        f' pipeline_no_detection_fuse_us={own["no_detection"]["fuse_us"]:.4g}')
    targets = {}
    if not args.pipeline_only:
        records = {kind: own[FUSION_OF[kind]]['records'] for kind in RELAY_OF}
        servers = start_servers(args, domain_id, records)
        try:
            runs = node_rates(args, servers, domain_id, truth, started + args.budget - 10.0)
        finally:
            stats = stop_servers(servers)
        fusers = list(RELAY_OF)
        rates = {kind: _median(runs[kind], 'msg_per_s') for kind in KINDS}
        ratio = {kind: statistics.median(f['msg_per_s'] / r['msg_per_s']
                                         for r, f in zip(runs[RELAY_OF[kind]], runs[kind]))
                 for kind in fusers}
        cpu_ratio = {kind: (_median(runs[RELAY_OF[kind]], 'cpu_us')
                            / _median(runs[kind], 'cpu_us')) for kind in fusers}
        lost = int(sum(run['lost'] for kind in KINDS for run in runs[kind]))
        # A fuser that dropped messages from a full queue was timed on less work.
        shed = {k: (stats.get(k) or {}).get('queue_overflow', 0) for k in fusers}
        targets = {f'node_{SHORT[k]}': ratio[k] >= TARGET_RATIO[k] and not shed[k]
                   for k in fusers}
        rounds = len(runs['relay'])
        lines += [
            '',
            f'part 2, nodes over DDS: messages handled per second at {ROWS_PER_MESSAGE} '
            f'rows/message, counted in the node; closed loop, window {args.window}, input '
            f'depth {args.input_depth} (reliable), {rounds} rounds of {args.warmup:g} s '
            f'warm-up + {args.measure:g} s (medians; spread = min-max of the rounds); '
            'CPU/msg = node process CPU time per message handled',
            'node              |  msg/s | spread      | ratio | CPU/msg | CPU-time ratio | '
            'CPU node / driver | idle polls',
        ]
        for kind in KINDS:
            values = [run['msg_per_s'] for run in runs[kind]]
            ratio_text = ' 1.00' if kind not in RELAY_OF else f'{ratio[kind]:5.2f}'
            cpu_text = ' 1.00' if kind not in RELAY_OF else f'{cpu_ratio[kind]:5.2f}'
            lines.append(f'{LABELS[kind]:17s} | {rates[kind]:6.0f} | '
                         f'{_spread(values, "{:.0f}"):11s} | {ratio_text} | '
                         f'{_median(runs[kind], "cpu_us"):4.0f} us | {cpu_text:>14s} | '
                         f'{_median(runs[kind], "node_cpu") * 100:4.0f} % / '
                         f'{_median(runs[kind], "driver_cpu") * 100:3.0f} %       | '
                         f'{_median(runs[kind], "idle_polls") * 100:5.1f} %')
        lines.append('each round (msg/s, ' + ' / '.join(LABELS[k] for k in KINDS) + '): '
                     + '; '.join(
            '/'.join(f'{runs[k][i]["msg_per_s"]:.0f}' for k in KINDS) for i in range(rounds)))
        lines.append('(ratios against the relay on the same input topics; CPU-time ratio '
                     'relay/fuser: what the msg/s ratio would be on idle cores)')
        lines.append('fusion lag in the fuser, last input -> queues empty after a fusion (mean '
                     '/ max) and oldest input -> same (mean / max), messages per fusion; end to '
                     'end (probe behind a full window -> fused_landmarks holds it):')
        for kind in fusers:
            e2e = [run['e2e_lag_ms'] for run in runs[kind]
                   if not math.isnan(run['e2e_lag_ms'])]
            lines.append(f'  {LABELS[kind]:17s} {_median(runs[kind], "lag_ms"):6.1f} / '
                         f'{max(run["lag_max_ms"] for run in runs[kind]):6.1f} ms, '
                         f'{_median(runs[kind], "lag_oldest_ms"):6.1f} / '
                         f'{max(run["lag_oldest_max_ms"] for run in runs[kind]):6.1f} ms, '
                         f'{_median(runs[kind], "messages_per_fusion"):5.1f} msg; end to end '
                         f'{_median(runs[kind], "e2e_lag_ms"):6.0f} ms '
                         f'({_spread(e2e, "{:.0f}")}, {len(e2e)}/{len(runs[kind])} seen)')
        lines.append(f'lost messages {lost}')
        for kind in fusers:
            counts = stats.get(kind) or {}
            problems = {k: v for k, v in counts.items()
                        if v and not k.startswith('source_') and k not in (
                            'landmarks', 'maxrss_kb', 'hwm_kb', 'landmarks_confirmed')}
            lines.append(f'{LABELS[kind]} counters: {counts.get("source_messages_in")} '
                         f'messages in, {counts.get("source_fused")} rows fused, '
                         f'{counts.get("source_gated_out", 0)} gated out, '
                         f'{counts.get("landmarks")} landmarks; other counters '
                         f'{problems or "none"}')
        lines.append('peak memory, VmHWM of each node process (getrusage maxrss in brackets: '
                     "Linux carries the spawning process's RSS over exec into it): " + ', '.join(
                         f'{LABELS[k]} {_mb(stats[k].get("hwm_kb"))} '
                         f'({_mb(stats[k].get("maxrss_kb"))})' for k in KINDS))
        dropped = {k: f', {shed[k]} rows dropped from full queues' if shed[k] else ''
                   for k in fusers}
        lines.append('targets: ' + '; '.join(
            f'{LABELS[k]} msg/s >= {TARGET_RATIO[k]:.0%} of {LABELS[RELAY_OF[k]]} '
            f'({ratio[k]:.2f}{dropped[k]}): '
            f'{_common.verdict(targets[f"node_{SHORT[k]}"])}' for k in fusers))
        result += (f' relay_msg_per_s_{ROWS_PER_MESSAGE}={rates["relay"]:.6g}'
                   f' relay_{MANY_SOURCES}_sources_msg_per_s_{ROWS_PER_MESSAGE}='
                   f'{rates["relay_many"]:.6g}'
                   + ''.join(f' fuser_{SHORT[k]}_msg_per_s_{ROWS_PER_MESSAGE}={rates[k]:.6g}'
                             f' ratio_{SHORT[k]}_{ROWS_PER_MESSAGE}={ratio[k]:.4g}'
                             f' cpu_ratio_{SHORT[k]}={cpu_ratio[k]:.4g}'
                             f' lag_{SHORT[k]}_ms={_median(runs[k], "lag_ms"):.4g}'
                             f' e2e_lag_{SHORT[k]}_ms={_median(runs[k], "e2e_lag_ms"):.4g}'
                             for k in fusers)
                   + ''.join(f' peak_rss_{"fuser_" + SHORT[k] if k in RELAY_OF else k}_mb='
                             f'{(stats[k].get("hwm_kb") or 0) / 1024:.4g}' for k in KINDS)
                   + f' window={args.window} rounds={rounds} lost={lost}')
    seconds = time.perf_counter() - started
    lines.insert(1, _common.machine_line(host, None if args.pipeline_only else domain_id,
                                         os.getloadavg()[0]))
    lines += ['', f'run time {seconds:.1f} s',
              result + f' cpus={host["cpu_count"]} pass={int(all(targets.values()))}']
    print('\n'.join(lines))
    sys.stdout.flush()
    return {'pipeline': own, 'targets': targets, 'seconds': seconds}


if __name__ == '__main__':
    main()
    sys.exit(0)
