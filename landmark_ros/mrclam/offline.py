"""
The offline replay: the dataset through the pipeline objects of the nodes (ROS-free).

Per robot one ``observer.Observer`` and per fusion method one
``fuser.Fuser``, built from the very YAML sections the nodes read
(``ObserverConfig`` / ``FuserConfig.from_values``), are fed what the nodes receive in
``--through-nodes``: for every observation message (one per robot and measurement
stamp, ``Rows.messages``), in global time order with ties by robot number, the
robot's pose at exactly that stamp (``add_pose``), then the message
(``add_observations``); each ``LandmarkBatch`` the observer places goes to every fuser
(``add_landmarks``, source ``/robotN/landmarks``) and the fusers fuse their queues
every ``FUSE_CHUNK`` messages, or every ``max_queue_messages`` if fewer (``fuse_queued``:
a batch gives the same map as its rows one by one). Time is integer nanoseconds
(``Rows.stamps_ns``, the stamps the player publishes); float seconds appear only in the
report.

``sensor`` keeps both columns (``rb``) or drops one: ``range`` sends range-only rows,
``bearing`` bearing-only rows; the observers turn them into partial observations, which
go to every fuser's partial source ``/robotN/partial_observations``.
"""

from collections import Counter
from dataclasses import dataclass, replace
from typing import Dict, Iterator, List, Sequence, Tuple

from landmark_ros.eval.metrics import evaluate_association
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fuser.tracks import ASSOCIATION_COUNTERS
from landmark_ros.mrclam.report import method_result, MethodResult
from landmark_ros.observer.observer import (LandmarkBatch, NOT_PROBLEMS, ObservationMessage,
                                            Observer)
import numpy as np

FUSE_CHUNK = 1024
"""Messages the fusers queue before ``Fuser.fuse_queued`` (at most ``max_queue_messages``)."""

FUSER_NOT_PROBLEMS = frozenset({'messages_in', 'observations_in', 'fused', 'gated_out',
                                'partial_in', 'partial_fused', 'partial_gated',
                                'landmarks_initialised', 'partial_superseded',
                                'landmarks_reinitialised', *ASSOCIATION_COUNTERS})

SENSORS = ('rb', 'range', 'bearing')
"""Values of ``sensor``: the columns of each observation message kept."""
"""Per-source fuser counters that are not row checks (gating is the fusion's result)."""


@dataclass
class OfflineRun:
    """What an offline replay leaves: the results and the pipeline objects that made them."""

    results: Dict[str, MethodResult]
    """Fusion method -> its map against the ground truth, in run order."""
    observers: List[Observer]
    """One per robot, in the order of ``Dataset.robots``."""
    fusers: Dict[str, Fuser]
    """Fusion method -> its fuser."""
    messages: int
    """Observation messages replayed."""

    @property
    def problems(self) -> Counter:
        """
        Return the rows the observer and fuser checks rejected, by reason.

        The observers' rejection counters plus the row checks of one fuser (every
        fuser checks the same rows); gating is not a check, it is in the results.
        """
        problems = Counter()
        for observer in self.observers:
            problems.update({k: v for k, v in observer.counters.counts.items()
                             if k not in NOT_PROBLEMS and v})
        for fuser in list(self.fusers.values())[:1]:
            for source in fuser.sources.values():
                problems.update({k: v for k, v in source.counts.items()
                                 if k not in FUSER_NOT_PROBLEMS and v})
        return problems


def observe(rows, observers: Sequence[Observer], P_pose,
            sensor: str = 'rb', hide_ids: bool = False) -> Iterator[Tuple[int, LandmarkBatch]]:
    """
    Feed every observation message to its robot's observer, in global time order.

    Each message (``Rows.messages``: the rows of one robot at one stamp) follows the
    robot's pose at exactly its stamp, as the player publishes them through the nodes.

    Parameters
    ----------
    rows : landmark_ros.mrclam.data.Rows
        Sightings in global time order.
    observers : sequence of Observer
        One per robot index of ``rows.robot``.
    P_pose : ndarray, shape (3, 3)
        Covariance of every pose [m^2, m rad, rad^2].
    sensor : str
        One of ``SENSORS``: ``range`` drops the bearings, ``bearing`` the ranges.
    hide_ids : bool
        Send the messages without their ``id`` column (landmarks without IDs); each
        batch's ``token`` is then the slice ``(a, b)`` of its rows in ``rows``.

    Yields
    ------
    robot : int
        Robot index.
    batch : LandmarkBatch
        What the observer placed (an empty batch when every row was rejected).

    """
    starts, ends = rows.messages()
    stamps_ns = rows.stamps_ns
    robots = rows.robot
    for a, b in zip(starts.tolist(), ends.tolist()):
        robot = int(robots[a])
        stamp_ns = int(stamps_ns[a])
        observer = observers[robot]
        batches = observer.add_pose(stamp_ns, rows.poses[a], P_pose, now_ns=stamp_ns)
        columns = {'id': rows.ids[a:b], 'range': rows.z[a:b, 0], 'bearing': rows.z[a:b, 1]}
        if sensor != 'rb':
            del columns['bearing' if sensor == 'range' else 'range']
        if hide_ids:
            del columns['id']
        batches += observer.add_observations(
            [ObservationMessage(stamp_ns, columns, token=(a, b))], now_ns=stamp_ns)
        for batch in batches:
            yield robot, batch


def run_offline(dataset, config, methods, chunk=FUSE_CHUNK, sensor='rb',
                hide_ids=False) -> OfflineRun:
    """
    Replay a dataset through the pipeline objects, one fuser per method.

    Parameters
    ----------
    dataset : landmark_ros.mrclam.data.Dataset
        The loaded dataset.
    config : landmark_ros.mrclam.config.ReplayConfig
        Observer and fuser parameters (the fuser's ``fusion`` is replaced by each
        method) and the pose covariance.
    methods : sequence of str
        Fusion methods (``fusion.landmark_map.FUSION_METHODS``).
    chunk : int
        Messages the fusers queue between two ``fuse_queued`` calls, capped at the
        fuser's ``max_queue_messages`` so no queue overflows; the maps do not depend
        on it.
    sensor : str
        One of ``SENSORS``.
    hide_ids : bool
        Strip the IDs before the observers: the fusers associate the sightings, and
        each result gets its ``association`` (``eval.metrics.evaluate_association``);
        matched tracks take their true landmark's ID in the records.

    Returns
    -------
    OfflineRun

    """
    rows = dataset.rows()
    observers = [Observer(config.observer) for _ in dataset.robots]
    if sensor not in SENSORS:
        raise ValueError(f'sensor must be one of {SENSORS}, got {sensor!r}')
    partial_observation_topics = [topic.rsplit('/', 1)[0] + '/partial_observations'
                                  for topic in rows.topics]
    fusers = {method: Fuser(replace(config.fuser, fusion=method), rows.topics,
                            partial_sources=partial_observation_topics)
              for method in methods}
    limit = max(1, min(int(chunk), config.fuser.max_queue_messages))
    queued = messages = 0
    sightings: Dict[str, list] = {method: [] for method in methods}
    for fuser in fusers.values():
        fuser.association_log = [] if hide_ids else None
    for robot, batch in observe(rows, observers, config.P_pose, sensor, hide_ids):
        source = rows.topics[robot]
        for method, fuser in fusers.items():
            if len(batch.ids) or sensor == 'rb':
                added = fuser.add_landmarks(source, LandmarkMessage(
                    batch.stamp_ns, batch.ids, batch.m, batch.P, batch.P_dep,
                    classes=batch.classes, scan=batch.scan))
                if hide_ids and added:
                    a, b = batch.token
                    whole = added == b - a
                    sightings[method].append(
                        (rows.ids[a:b], batch.m, batch.P) if whole else None)
            if len(batch.partial_observations):
                fuser.add_partial_observations(partial_observation_topics[robot], batch.stamp_ns,
                                               batch.partial_observations.columns())
        messages += 1
        queued += 1
        if queued >= limit:
            for fuser in fusers.values():
                fuser.fuse_queued()
            queued = 0
    results = {}
    for method, fuser in fusers.items():
        fuser.fuse_queued()
        counts = [source.counts for source in fuser.sources.values()]
        records = fuser.map.to_records()
        association = None
        if hide_ids:
            association = _association(fuser, sightings[method], dataset.landmarks)
            for record in records:
                record['track_id'] = record['id']
                record['id'] = association.track_to_true.get(record['id'], record['id'])
        result = method_result(method, records, dataset.landmarks,
                               sum(c['fused'] + c['partial_fused'] for c in counts),
                               sum(c['gated_out'] + c['partial_gated'] for c in counts))
        result.sensor = sensor
        result.landmarks_initialised = sum(c['landmarks_initialised'] for c in counts)
        result.association = association
        if fuser.moves is not None:
            result.moves = (sum(fuser.moves.alarms.values()), fuser.moves.tested)
        results[method] = result
    return OfflineRun(results, observers, fusers, messages)


def _association(fuser, sightings, truth):
    """Score a fuser's association log against the true IDs of the sightings."""
    log = fuser.association_log
    if len(log) != len(sightings):
        raise RuntimeError(f'{len(log)} associated messages for {len(sightings)} queued')
    parts = [(np.array([fuser.tracker.resolve(i) for i in entry[2].tolist()], np.int64),
              *sighting) for entry, sighting in zip(log, sightings) if sighting is not None]
    assigned = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    true_ids = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.int64)
    z = np.concatenate([p[2] for p in parts]) if parts else np.zeros((0, 2))
    R = np.concatenate([p[3] for p in parts]) if parts else np.zeros((0, 2, 2))
    ids, m = fuser.snapshot()[:2]
    return evaluate_association(assigned, true_ids, z, R, ids, m, truth)
