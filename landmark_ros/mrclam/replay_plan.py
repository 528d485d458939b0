"""
The plan of the replay through the nodes, without ROS: arguments, order, checks.

What ``player`` starts (``observer_arguments``, ``fuser_arguments`` with the transport
overrides ``OBSERVER_TRANSPORT`` and ``FUSER_TRANSPORT``), the order its clouds must keep
at the fusers (``dependencies``, or ``sequential`` without IDs), the partial observation clouds
each observer will publish (``expected_partial``), and what it reads back
(``hidden_association``, ``cpu_seconds``). ``plan_clouds`` gathers the per-cloud
schedule ``Player`` follows.
"""

from collections import Counter
from dataclasses import dataclass, fields, replace
import os
from typing import List, Optional, Tuple

from landmark_ros.eval.metrics import evaluate_association
from landmark_ros.mrclam.offline import observe
from landmark_ros.observer.observer import Observer
from landmark_ros.pipeline.config import FuserConfig
import numpy as np


class ReplayError(RuntimeError):
    """The replay through the nodes failed (process exit, stall, lost message)."""


@dataclass(frozen=True)
class PlayOptions:
    """
    How ``Player`` plays the dataset.

    Attributes
    ----------
    progress : bool or None
        The progress bar: None only on a terminal, True always, False never.
    stall_timeout_s : float
        The replay fails after this long without progress [s].
    hide_ids : bool
        Send every row as ``UNKNOWN_ID``, clouds in global time order (``sequential``).
    sensor : str
        ``rb``, ``range`` or ``bearing``: the column(s) each cloud carries.

    """

    progress: Optional[bool] = None
    stall_timeout_s: float = 60.0
    hide_ids: bool = False
    sensor: str = 'rb'


def cpu_seconds(pids):
    """Return the CPU time (user + system) of running processes, from /proc (Linux)."""
    ticks = os.sysconf('SC_CLK_TCK') if hasattr(os, 'sysconf') else 100
    result = {}
    for name, pid in pids.items():
        try:
            with open(f'/proc/{pid}/stat') as stream:
                parts = stream.read().rsplit(')', 1)[1].split()
            result[name] = (int(parts[11]) + int(parts[12])) / ticks
        except (OSError, IndexError, ValueError):
            pass
    return result


OBSERVER_TRANSPORT = {
    'input_depth': 1000, 'output_depth': 1000, 'max_pending': 1000,
    'pose_buffer_s': 3600.0, 'max_wait_s': 30.0, 'marker_rate_hz': 0.0,
    'diagnostics_period_s': 1.0,
}
"""Observer parameters the replay sets on top of the config file (transport only)."""

OBSERVER_WINDOW = 8
"""Observation clouds in flight per observer (sent, no ``landmarks`` output yet)."""

FUSER_WINDOW = 64
"""Clouds per robot sent but not yet known to be taken by every fuser."""

FUSER_BATCH = FUSER_WINDOW if 'max_batch_messages' in {
    spec.name for spec in fields(FuserConfig)} else 1
"""Clouds of one source a fuser callback takes at most (its ``max_batch_messages``)."""

FUSER_TRANSPORT = {
    'update_period_s': 0.05, 'publish_rate_hz': 5.0, 'max_queue_messages': 100000,
    'input_depth': 1000, 'diagnostics_period_s': 0.25, 'source_timeout_s': 86400.0,
    'autosave_period_s': 0.0,
}
"""Fuser parameters the replay sets on top of the config file (besides topics, method)."""
if FUSER_BATCH > 1:
    FUSER_TRANSPORT['max_batch_messages'] = FUSER_BATCH


def _param(name, value):
    if isinstance(value, bool):
        text = 'true' if value else 'false'
    elif isinstance(value, (list, tuple)):
        text = '[' + ', '.join(f"'{v}'" for v in value) + ']'
    else:
        text = str(value)
    return ['-p', f'{name}:={text}']


def observer_arguments(robot, config_path):
    """Return the ROS arguments of a robot's observer process."""
    ns = f'/{robot.name}'
    arguments = ['-r', f'__ns:={ns}', '--params-file', str(config_path)]
    for name, value in OBSERVER_TRANSPORT.items():
        arguments += _param(name, value)
    for topic in ('pose', 'observations'):
        arguments += _param(f'qos_overrides.{ns}/{topic}.subscription.reliability',
                            'reliable')
    return arguments


def fuser_arguments(method, topics, config_path, map_path, partial_observation_topics=None):
    """Return the ROS arguments of one fuser process (with ``partial_observation_topics``)."""
    arguments = ['-r', f'__ns:=/mrclam/{method}', '--params-file', str(config_path)]
    extra = {} if partial_observation_topics is None else {
        'partial_observation_topics': list(partial_observation_topics)}
    for name, value in dict(FUSER_TRANSPORT, input_topics=list(topics), fusion=method,
                            map_file=str(map_path), **extra).items():
        arguments += _param(name, value)
    return arguments


def partial_topic(landmarks_topic):
    """Return a robot's ``partial_observations`` topic beside its ``landmarks`` one."""
    return landmarks_topic.rsplit('/', 1)[0] + '/partial_observations'


def expected_partial(rows, config, sensor):
    """
    Return, per cloud, whether its observer publishes a ``partial_observations`` cloud.

    The observers' own pipeline (``offline.observe``, fresh ``Observer`` objects of
    the config) on the very clouds the player sends: a cloud gives partial observations when
    some of its partial rows pass the observer's checks.

    Returns
    -------
    ndarray of bool, shape (K,)
        In the order of ``rows.messages()``.

    """
    count = len(rows.messages()[0])
    if sensor == 'rb':
        return np.zeros(count, bool)
    robots = int(rows.robot.max()) + 1 if len(rows) else 0
    observers = [Observer(config.observer) for _ in range(robots)]
    flags = [bool(len(batch.partial_observations))
             for _, batch in observe(rows, observers, config.P_pose, sensor)]
    if len(flags) != count:
        raise ReplayError(f'the observers placed {len(flags)} of {count} clouds offline')
    return np.array(flags, bool)


def dependencies(rows, starts, ends):
    """
    Return, per cloud, the clouds of other robots it must follow at the fuser.

    For each landmark of cloud ``j``, the last earlier cloud with that landmark: when
    it is another robot's, ``j`` must reach the fuser after it. Earlier clouds with
    the landmark need no entry: that cloud itself followed them (the clouds of one
    robot stay in order by themselves).

    Returns
    -------
    requirements : list of tuple of (int, int)
        Per cloud, ``(robot, local)`` pairs: the cloud ``local`` (index among the
        clouds of robot index ``robot``) must be taken by the fusers first; one pair
        per robot, the latest.
    local : ndarray of int, shape (K,)
        Index of each cloud among its robot's clouds.

    """
    count = len(starts)
    msg_robot = rows.robot[starts].tolist()
    local = np.zeros(count, np.int64)
    seen = Counter()
    last = {}
    requirements = []
    ids = rows.ids.tolist()
    for j in range(count):
        r = msg_robot[j]
        local[j] = seen[r]
        seen[r] += 1
        need = {}
        for landmark in set(ids[starts[j]:ends[j]]):
            i = last.get(landmark, -1)
            if i >= 0 and msg_robot[i] != r:
                need[msg_robot[i]] = max(need.get(msg_robot[i], -1), int(local[i]))
            last[landmark] = j
        requirements.append(tuple(sorted(need.items())))
    return requirements, local


def sequential(msg_robot, local):
    """
    Return, per cloud, the cloud before it when another robot's: one global order.

    Without IDs (``--hide-ids``) a row may go to any landmark and new tracks take IDs
    in the order they start, so every fuser must take the clouds of all robots in
    global time order, not only the clouds of each landmark: each cloud follows the
    one before it (the clouds of one robot stay in order by themselves).

    Parameters
    ----------
    msg_robot : ndarray of int, shape (K,)
        Robot index of each cloud.
    local : ndarray of int, shape (K,)
        Index of each cloud among its robot's clouds (``dependencies``).

    Returns
    -------
    list of tuple of (int, int)
        As the requirements of ``dependencies``.

    """
    robots = np.asarray(msg_robot).tolist()
    return [((robots[j - 1], int(local[j - 1])),) if j and robots[j - 1] != robots[j]
            else () for j in range(len(robots))]


def hidden_association(records, truth):
    """
    Match a map built without IDs to the true landmarks; rename its records.

    Each record keeps its own ID as ``track_id`` and takes the ID of the true landmark
    its track is matched to (``eval.metrics.evaluate_association``: optimal assignment
    on positions within 1 m), as the offline replay does.

    Returns
    -------
    AssociationSummary
        The map's figures (tracks, GOSPA, matching); no sighting is scored (the
        nodes do not publish which track each sighting went to): the accuracies are
        NaN until the caller fills them in.

    """
    ids = np.array([r['id'] for r in records], np.int64)
    m = np.array([r['mean'] for r in records], np.float64).reshape(-1, 2)
    summary = evaluate_association(np.zeros(0, np.int64), np.zeros(0, np.int64),
                                   np.zeros((0, 2)), np.zeros((0, 2, 2)), ids, m, truth)
    summary = replace(summary, association_accuracy=float('nan'),
                      oracle_accuracy=float('nan'))
    for record in records:
        record['track_id'] = record['id']
        record['id'] = summary.track_to_true.get(record['id'], record['id'])
    return summary


def domain_id_for(pid=None):
    """Return the private ROS_DOMAIN_ID of a replay: 100 to 149, from the process ID."""
    return 100 + (os.getpid() if pid is None else pid) % 50


@dataclass(frozen=True)
class CloudPlan:
    """
    The per-cloud schedule of a replay (``K`` clouds, ``R`` robots).

    Attributes
    ----------
    starts, ends : ndarray of int, shape (K,)
        Row ranges of the clouds (``rows.messages()``).
    msg_robot : ndarray of int, shape (K,)
        Robot index of each cloud.
    msg_stamps_ns : ndarray of int, shape (K,)
        Stamp of each cloud [ns].
    requirements : list of tuple of (int, int)
        Per cloud, what it must follow (``dependencies``, or ``sequential``).
    local : ndarray of int, shape (K,)
        Index of each cloud among its robot's clouds.
    totals : list of int
        Clouds per robot.
    robot_clouds : list of list of int
        Per robot, its clouds' indices.
    expected_ns : list of list of int
        Per robot, the stamps of its clouds [ns] (its observer's outputs, in order).
    partial_ns : list of list of int
        Per robot, the stamps of the partial observation clouds its observer publishes [ns].
    partial_before : list of list of int
        Per robot, partial observation clouds among its first ``k`` clouds, ``k`` = 0 to its total.

    """

    starts: np.ndarray
    ends: np.ndarray
    msg_robot: np.ndarray
    msg_stamps_ns: np.ndarray
    requirements: List[Tuple[Tuple[int, int], ...]]
    local: np.ndarray
    totals: List[int]
    robot_clouds: List[List[int]]
    expected_ns: List[List[int]]
    partial_ns: List[List[int]]
    partial_before: List[List[int]]


def plan_clouds(rows, config, robot_count, options):
    """
    Return the ``CloudPlan`` of a replay of ``rows`` by ``robot_count`` robots.

    ``options`` (``PlayOptions``): ``hide_ids`` orders every cloud after the one before
    it (``sequential``), ``sensor`` decides which clouds give partial observation clouds
    (``expected_partial``).
    """
    starts, ends = rows.messages()
    msg_robot = rows.robot[starts]
    msg_stamps_ns = rows.stamps_ns[starts]
    requirements, local = dependencies(rows, starts, ends)
    if options.hide_ids:
        requirements = sequential(msg_robot, local)
    robots = range(robot_count)
    expected_ns = [[] for _ in robots]
    for j in range(len(starts)):
        expected_ns[msg_robot[j]].append(int(msg_stamps_ns[j]))
    flags = expected_partial(rows, config, options.sensor)
    return CloudPlan(
        starts=starts, ends=ends, msg_robot=msg_robot, msg_stamps_ns=msg_stamps_ns,
        requirements=requirements, local=local,
        totals=np.bincount(msg_robot, minlength=robot_count).tolist(),
        robot_clouds=[np.flatnonzero(msg_robot == r).tolist() for r in robots],
        expected_ns=expected_ns,
        # Per robot: partial observation stamps expected, and how many among its first k.
        partial_ns=[msg_stamps_ns[msg_robot == r][flags[msg_robot == r]].tolist()
                    for r in robots],
        partial_before=[np.concatenate(([0], np.cumsum(flags[msg_robot == r]))).tolist()
                        for r in robots])
