"""
Landmarks without IDs: association of unlabelled rows and their tracks (ROS-free).

A landmark row whose ID is ``rows.UNKNOWN_ID`` carries no landmark identity. Per
message, at fuse time and in arrival order, the ``Tracker`` pairs the unlabelled rows
with the confirmed landmarks and the tentative tracks of their class
(``core.association``: nearest neighbour, global nearest neighbour or JCBB on the
message's joint covariance, built from its ``Scan``). A paired row takes that
landmark's ID; an unpaired one starts a tentative track with a new ID from the
allocator (``first_new_id`` upwards, never reused, never an ID the map already knows).
The rows then go through ``LandmarkMap.update`` exactly like labelled rows: gating,
confirmation by ``min_observations`` agreeing rows and the fusion stay one
implementation. A tentative track not confirmed within ``tentative_timeout_s`` (of
observation stamps) is deleted (``LandmarkMap.forget``).

Symbols
-------
z : unlabelled rows of one message in the world, shape (N, 2) [m].
R : their total covariances, shape (N, 2, 2) [m^2].
C_z : their joint covariance, shape (2N, 2N) [m^2] (``association.scan_covariance``).
"""

from collections import Counter
from dataclasses import dataclass
from typing import Dict, List, Optional

from landmark_ros.core.association import (candidates, global_nearest_neighbour, jcbb,
                                           LandmarkIndex, nearest_neighbour,
                                           scan_covariance)
from landmark_ros.core.landmark_map import LandmarkMap, UpdateResult
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import MAX_LABEL_ID, UNKNOWN_ID
import numpy as np
from numpy.typing import NDArray

ASSOCIATION_COUNTERS = ('associated', 'new_tentative', 'confirmed', 'deleted', 'merged',
                        'ambiguous', 'jcbb_fallback')
"""Per-source counters of the association (throughput, not rejections)."""


@dataclass(frozen=True)
class Scan:
    """
    What the joint covariance of one message's rows needs (``association.scan_covariance``).

    Attributes
    ----------
    robot_xy : ndarray, shape (2,) [m]
        Robot position the message was observed from.
    P_pose : ndarray, shape (3, 3)
        Covariance of the robot pose (x [m], y [m], theta [rad]).
    R_bias : ndarray, shape (2, 2), optional
        Covariance of the sensor bias (range [m^2], bearing [rad^2]); None for none.
    sensor_xy : ndarray, shape (2,) [m], optional
        Sensor position in the world (with ``R_bias``).

    """

    robot_xy: NDArray[np.float64]
    P_pose: NDArray[np.float64]
    R_bias: Optional[NDArray[np.float64]] = None
    sensor_xy: Optional[NDArray[np.float64]] = None


@dataclass
class _Track:
    """A tentative track: the latest row paired with it (mean [m], covariance [m^2])."""

    m: NDArray[np.float64]
    P: NDArray[np.float64]
    landmark_class: int
    first_ns: int
    source: str


class Tracker:
    """
    Give unlabelled rows landmark IDs by data association; keep their tentative tracks.

    Parameters
    ----------
    config : FuserConfig
        ``association``, ``association_gate_probability``, ``first_new_id``,
        ``tentative_timeout_s``, ``ambiguous_rows``.

    """

    def __init__(self, config: FuserConfig) -> None:
        self.config = config
        self.next_id = int(config.first_new_id)
        """The next ID the allocator tries (persisted in the map file)."""
        self.classes: Dict[int, int] = {}
        """Class of each landmark ID with a class other than 0."""
        self.tentative: Dict[int, _Track] = {}
        """Tentative tracks started by unlabelled rows, by ID."""
        self.dirty = True
        """Whether the index must be rebuilt before the next association."""
        self._index: Optional[LandmarkIndex] = None
        self._index_ids = np.empty(0, np.int64)

    def reset(self) -> None:
        """Forget the tracks and classes; the allocator goes on (IDs are never reused)."""
        self.classes.clear()
        self.tentative.clear()
        self.dirty = True

    def class_of(self, ids: NDArray[np.int64]) -> NDArray[np.int64]:
        """Return the class of each landmark ID, shape (K,) (0 when none was given)."""
        if not self.classes:
            return np.zeros(len(ids), np.int64)
        return np.array([self.classes.get(i, 0) for i in np.asarray(ids).tolist()], np.int64)

    def note_classes(self, ids: NDArray[np.int64], classes: NDArray[np.int64]) -> None:
        """Remember the classes of labelled rows (the first one given for an ID wins)."""
        labelled = (classes != 0) & (ids != UNKNOWN_ID)
        for landmark_id, landmark_class in zip(ids[labelled].tolist(),
                                               classes[labelled].tolist()):
            self.classes.setdefault(landmark_id, landmark_class)

    def allocate(self, landmark_map: LandmarkMap) -> int:
        """
        Return a new landmark ID: never given before, unknown to the map.

        Raises
        ------
        ValueError
            If the IDs up to ``MAX_LABEL_ID`` are used up.

        """
        while landmark_map.known(np.array([self.next_id], np.int64))[0]:
            self.next_id += 1
        if self.next_id > MAX_LABEL_ID:
            raise ValueError('no landmark ID left to allocate')
        landmark_id = self.next_id
        self.next_id += 1
        return landmark_id

    def _rebuild(self, landmark_map: LandmarkMap) -> None:
        snapshot = landmark_map.snapshot()
        ids = [snapshot.ids]
        m, P = [snapshot.m], [snapshot.P]
        classes = [self.class_of(snapshot.ids)]
        if self.tentative:
            tracks = list(self.tentative.items())
            ids.append(np.array([i for i, _ in tracks], np.int64))
            m.append(np.array([t.m for _, t in tracks]).reshape(-1, 2))
            P.append(np.array([t.P for _, t in tracks]).reshape(-1, 2, 2))
            classes.append(np.array([t.landmark_class for _, t in tracks], np.int64))
        self._index_ids = np.concatenate(ids)
        self._index = LandmarkIndex(np.concatenate(m), np.concatenate(P),
                                    np.concatenate(classes))
        self.dirty = False

    def associate(self, landmark_map: LandmarkMap, source: str, z: NDArray[np.float64],
                  R: NDArray[np.float64], classes: NDArray[np.int64], scan: Optional[Scan],
                  stamp_ns: int, counts: Counter) -> NDArray[np.int64]:
        """
        Give the unlabelled rows of one message landmark IDs.

        Parameters
        ----------
        landmark_map : LandmarkMap
            The map as it is before this message.
        source : str
            The message's source.
        z : ndarray, shape (N, 2) [m]
            The unlabelled rows.
        R : ndarray, shape (N, 2, 2) [m^2]
            Their total covariances.
        classes : ndarray of int, shape (N,)
            Their classes.
        scan : Scan or None
            The message's pose (and bias) terms; None treats the rows as independent.
        stamp_ns : int
            The message stamp [ns].
        counts : collections.Counter
            The source's counters (``ASSOCIATION_COUNTERS``), updated.

        Returns
        -------
        ndarray of int64, shape (N,)
            The ID of each row; -1 for a row dropped as ambiguous.

        """
        if self.dirty or self._index is None:
            self._rebuild(landmark_map)
        index = self._index
        probability = self.config.association_gate_probability
        cands = candidates(index, z, R, classes, probability)
        method = self.config.association
        if method == 'nearest_neighbour':
            result = nearest_neighbour(cands)
        elif method == 'global_nearest_neighbour':
            result = global_nearest_neighbour(cands)
        else:
            C_z = None
            if scan is not None:
                try:
                    C_z = scan_covariance(z, R, scan.robot_xy, scan.P_pose, scan.R_bias,
                                          scan.sensor_xy)
                except ValueError:
                    C_z = None
            if C_z is None:
                C_z = scan_covariance(z, R, np.zeros(2), np.zeros((3, 3)))
            result = jcbb(cands, index, z, C_z)
            if result.fallback:
                counts['jcbb_fallback'] += 1
        ids = np.full(len(z), -1, np.int64)
        assigned = result.assignment >= 0
        ids[assigned] = self._index_ids[result.assignment[assigned]]
        ambiguous = _open_ambiguity(cands, result)
        if len(ambiguous):
            counts['ambiguous'] += len(ambiguous)
            if self.config.ambiguous_rows == 'skip':
                ids[ambiguous] = -1
                assigned[ambiguous] = False
        counts['associated'] += int(assigned.sum())
        for i in np.flatnonzero(assigned).tolist():
            track = self.tentative.get(int(ids[i]))
            if track is not None:
                track.m, track.P = z[i].copy(), R[i].copy()
                self.dirty = True
        skipped = np.zeros(len(z), bool)
        if self.config.ambiguous_rows == 'skip':
            skipped[ambiguous] = True
        for i in np.flatnonzero(~assigned & ~skipped).tolist():
            landmark_id = self.allocate(landmark_map)
            ids[i] = landmark_id
            landmark_class = int(classes[i])
            if landmark_class:
                self.classes[landmark_id] = landmark_class
            self.tentative[landmark_id] = _Track(z[i].copy(), R[i].copy(), landmark_class,
                                                 int(stamp_ns), source)
            counts['new_tentative'] += 1
            self.dirty = True
        return ids

    def after_update(self, result: UpdateResult,
                     counts_of: Dict[str, Counter]) -> None:
        """Note the tracks an update confirmed; mark the index stale if the map changed."""
        for landmark_id in result.confirmed:
            track = self.tentative.pop(landmark_id, None)
            if track is not None:
                counts_of[track.source]['confirmed'] += 1
        if result.changed:
            self.dirty = True

    def expire(self, landmark_map: LandmarkMap, now_ns: int,
               counts_of: Dict[str, Counter]) -> List[int]:
        """
        Delete the tentative tracks older than ``tentative_timeout_s``; return their IDs.

        Parameters
        ----------
        landmark_map : LandmarkMap
            Where their buffered rows are forgotten.
        now_ns : int
            The newest observation stamp fused [ns].
        counts_of : dict of str to collections.Counter
            Counters by source; ``deleted`` is counted on the source that started a track.

        Returns
        -------
        list of int

        """
        timeout_ns = self.config.tentative_timeout_s * 1e9
        if not self.tentative or timeout_ns <= 0.0:
            return []
        old = [landmark_id for landmark_id, track in self.tentative.items()
               if now_ns - track.first_ns > timeout_ns]
        if old:
            landmark_map.forget(np.array(old, np.int64))
            for landmark_id in old:
                counts_of[self.tentative.pop(landmark_id).source]['deleted'] += 1
            self.dirty = True
        return old


def _open_ambiguity(cands, result) -> NDArray[np.intp]:
    """
    Return the ambiguous rows of an association that have a free alternative.

    ``Association.ambiguous`` also lists rows whose only alternatives are landmarks
    another row of the message took: swapping to one of them is no one-to-one
    hypothesis (nearest neighbour aside, which may pair two rows with one landmark).
    A row stays ambiguous when some other candidate of it is paired with no row.
    """
    if not len(result.ambiguous) or result.method == 'nn':
        return np.asarray(result.ambiguous, np.intp)
    taken = result.assignment[result.assignment >= 0]
    free = ~np.isin(cands.landmarks, taken)
    rows_with_free = np.unique(cands.rows[free & (cands.landmarks != result.assignment[
        cands.rows])])
    return np.intersect1d(result.ambiguous, rows_with_free).astype(np.intp)
