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

Determinism. Expiry and merging are checked per message without an ID, in the fuser's
sequence order (expiry before its association, against the newest stamp fused so far,
``now_ns``; merging after its update, for the landmarks it changed), never at the
boundaries of a ``fuse_queued`` batch: the map depends on the order of the messages
only, not on when the fuser's timer fused them (the nodes and the offline replay agree).

Symbols
-------
z : unlabelled rows of one message in the world, shape (N, 2) [m].
R : their total covariances, shape (N, 2, 2) [m^2].
C_z : their joint covariance, shape (2N, 2N) [m^2] (``association.scan_covariance``).
"""

from collections import Counter
from typing import Any, Dict, Iterable, List, Optional, Set, Tuple

from landmark_ros.core.association import (Association, Candidates, candidates,
                                           global_nearest_neighbour, LandmarkIndex,
                                           nearest_neighbour, scan_covariance)
from landmark_ros.core.gating import chi2_threshold, difference_mahalanobis_sq
from landmark_ros.core.joint_compatibility import jcbb
from landmark_ros.fuser import track_file
from landmark_ros.fuser.track_file import Track
from landmark_ros.fuser.track_score import (one_landmark_by_sightings, SourceStatistics,
                                            sprt_thresholds, start_score,
                                            team_detection_probability,
                                            together_log_likelihood_ratio)
from landmark_ros.fuser.track_screen import ScoredTracks
from landmark_ros.fusion.landmark_map import LandmarkMap, MapSnapshot, UpdateResult
from landmark_ros.pipeline.config import FuserConfig
from landmark_ros.pipeline.rows import MAX_LABEL_ID, UNKNOWN_ID
from landmark_ros.pipeline.scan import Scan
import numpy as np
from numpy.typing import NDArray

__all__ = ['ASSOCIATION_COUNTERS', 'Tracker', 'together_log_likelihood_ratio']

ASSOCIATION_COUNTERS = ('associated', 'new_tentative', 'confirmed', 'deleted', 'merged',
                        'ambiguous', 'jcbb_fallback')
"""Per-source counters of the association (throughput, not rejections)."""


class Tracker(ScoredTracks):
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
        self.tentative: Dict[int, Track] = {}
        """Tentative tracks started by unlabelled rows, by ID."""
        self.dirty = True
        """Whether the index must be rebuilt before the next association."""
        self._indices: List[Tuple[LandmarkIndex, NDArray[np.int64]]] = []
        """``(LandmarkIndex, IDs)`` of the confirmed landmarks, then of the tentative tracks."""
        self.owned: Set[int] = set()
        """IDs this tracker allocated (only these are ever merged)."""
        self.sightings: Dict[int, int] = {}
        """Messages with a row that went to each owned ID (the merge test)."""
        self.together: Dict[int, Dict[int, int]] = {}
        """``together[a][b]``: messages with rows that went to both owned IDs ``a`` and
        ``b`` (symmetric; pairs never seen together are absent)."""
        self.apart: Dict[int, Dict[int, int]] = {}
        """``apart[a][b]``: messages, after ``a`` and ``b`` first met, that gave a row to
        one of the two only (symmetric; kept for the pairs in ``together``)."""
        self.merged_into: Dict[int, int] = {}
        """A merged (retired) ID -> the ID it was merged into."""
        self.now_ns: Optional[int] = None
        """The newest observation stamp fused so far [ns] (the clock of expiry)."""
        self.rejected_tracks: List[Tuple[int, List[str]]] = []
        """Tentative tracks the last ``restore`` dropped: ``(ID, reasons)``."""
        self.statistics: Dict[str, SourceStatistics] = {}
        """Per source: its view, clutter density and detection probability estimates
        (``fuser.track_score``; persisted)."""
        self.scores: Dict[int, List[float]] = {}
        """``[score, peak]`` of the owned confirmed tracks seen in view (``track_screen``)."""
        self.deleted: List[Tuple[int, NDArray[np.float64], NDArray[np.float64],
                                 NDArray[np.float64]]] = []
        """Confirmed tracks deleted by their score: ``(ID, m, P, P_dep)``, last estimates."""

    def reset(self) -> None:
        """Forget the tracks and classes; the allocator goes on (IDs are never reused)."""
        self.classes.clear()
        self.tentative.clear()
        self.owned.clear()
        self.sightings.clear()
        self.together.clear()
        self.apart.clear()
        self.merged_into.clear()
        self.statistics.clear()
        self.scores.clear()
        self.deleted.clear()
        self.now_ns = None
        self.rejected_tracks = []
        self.dirty = True

    def advance(self, stamp_ns: int) -> int:
        """Move the expiry clock to ``stamp_ns`` if it is newer; return the clock [ns]."""
        if self.now_ns is None or stamp_ns > self.now_ns:
            self.now_ns = int(stamp_ns)
        return self.now_ns

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

        With ``shard_count`` > 1 only IDs equal to ``shard_index`` modulo
        ``shard_count`` are given (the labelled rule: each shard owns its IDs).

        Raises
        ------
        ValueError
            If the IDs up to ``MAX_LABEL_ID`` are used up.

        """
        count, index = self.config.shard_count, self.config.shard_index
        if count > 1 and self.next_id % count != index:
            # A shard gives IDs of its own residue only: shards never give one ID twice.
            self.next_id += (index - self.next_id) % count
        while landmark_map.known(np.array([self.next_id], np.int64))[0]:
            self.next_id += count if count > 1 else 1
        if self.next_id > MAX_LABEL_ID:
            raise ValueError('no landmark ID left to allocate')
        landmark_id = self.next_id
        self.next_id += 1
        self.owned.add(landmark_id)
        return landmark_id

    def _rebuild(self, landmark_map: LandmarkMap) -> None:
        snapshot = landmark_map.snapshot()
        tracks = list(self.tentative.items())
        tentative_ids = np.array([i for i, _ in tracks], np.int64)
        self._indices = [
            (LandmarkIndex(snapshot.m, snapshot.P, self.class_of(snapshot.ids)), snapshot.ids),
            (LandmarkIndex(np.array([t.m for _, t in tracks]).reshape(-1, 2),
                           np.array([t.P for _, t in tracks]).reshape(-1, 2, 2),
                           np.array([t.landmark_class for _, t in tracks], np.int64)),
             tentative_ids)]
        self.dirty = False

    def associate(self, landmark_map: LandmarkMap, source: str, z: NDArray[np.float64],
                  R: NDArray[np.float64], classes: NDArray[np.int64], scan: Optional[Scan],
                  stamp_ns: int, counts: Counter[str]) -> NDArray[np.int64]:
        """
        Give the unlabelled rows of one message landmark IDs.

        The rows are associated with the confirmed landmarks first; those left unpaired
        (not those dropped as ambiguous) then with the tentative tracks, by the same
        method; the rest start tentative tracks.

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
        if self.dirty or not self._indices:
            self._rebuild(landmark_map)
        ids = np.full(len(z), -1, np.int64)
        skipped = np.zeros(len(z), bool)
        for index, index_ids in self._indices:
            rows = np.flatnonzero((ids < 0) & ~skipped)
            if not len(rows) or not len(index):
                continue
            paired, ambiguous = self._pair(index, z[rows], R[rows], classes[rows], scan,
                                           counts)
            ids[rows[paired >= 0]] = index_ids[paired[paired >= 0]]
            skipped[rows[ambiguous]] = True
        assigned = ids >= 0
        counts['associated'] += int(assigned.sum())
        stats = list(self.statistics.values())
        born = []
        for i in np.flatnonzero(~assigned & ~skipped).tolist():
            landmark_id = self.allocate(landmark_map)
            born.append(landmark_id)
            ids[i] = landmark_id
            landmark_class = int(classes[i])
            if landmark_class:
                self.classes[landmark_id] = landmark_class
            self.tentative[landmark_id] = Track(z[i].copy(), R[i].copy(), landmark_class,
                                                int(stamp_ns), source,
                                                score=start_score(
                                                    sum(s.confirmed for s in stats),
                                                    sum(s.deleted for s in stats)))
            counts['new_tentative'] += 1
            self.dirty = True
        self.note_sightings(ids, born)
        return ids

    def note_sightings(self, ids: NDArray[np.int64], born: Iterable[int] = ()) -> None:
        """
        Count one message's sightings of owned IDs, alone and by pairs (the merge test).

        A track started by a row of the message does not meet the message's other
        tracks in it: a row starts a track because no track took it, so every
        duplicate started by a clutter row beside its landmark meets the landmark's
        track in the message that started it. One landmark gives one row per scan, and
        that meeting says one of the two rows was not the landmark's; it is no evidence
        of two landmarks. The meetings after it are (``one_landmark``).

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            The IDs the message's rows went to (others than owned ones are ignored;
            an ID given to several rows counts once).
        born : iterable of int
            The IDs the message's rows started (allocated for this message).

        """
        seen = sorted({i for i in np.asarray(ids).tolist() if i in self.owned})
        new, present = set(born), set(seen)
        for a in seen:
            self.sightings[a] = self.sightings.get(a, 0) + 1
            for b in self.together.get(a, {}):
                if b not in present:
                    alone = self.apart.setdefault(a, {})
                    alone[b] = alone.get(b, 0) + 1
                    self.apart.setdefault(b, {})[a] = alone[b]
            for b in seen:
                if b != a and a not in new and b not in new:
                    partners = self.together.setdefault(a, {})
                    partners[b] = partners.get(b, 0) + 1

    def _forget_counts(self, landmark_id: int) -> None:
        """Drop the sighting counts of an ID that left (deleted or merged)."""
        self.sightings.pop(landmark_id, None)
        for counts in (self.together, self.apart):
            for other in counts.pop(landmark_id, {}):
                counts[other].pop(landmark_id, None)
                if not counts[other]:
                    del counts[other]

    def _merge_counts(self, keep: int, drop: int) -> None:
        """
        Move the counts of ``drop`` to ``keep``, merged into it.

        The sightings of the merged track are those of either (the messages that saw
        both counted once); its co-occurrences with a third track add up, an upper
        bound (a message that saw all three counts twice), which errs on the side of
        keeping tracks apart.
        """
        both = self.together.get(keep, {}).get(drop, 0)
        self.sightings[keep] = (self.sightings.get(keep, 0) + self.sightings.get(drop, 0)
                                - both)
        for other, count in self.together.get(drop, {}).items():
            if other != keep:
                partners = self.together.setdefault(keep, {})
                partners[other] = partners.get(other, 0) + count
                self.together[other][keep] = partners[other]
        self._forget_counts(drop)

    def merge(self, landmark_map: LandmarkMap, counts: Counter,
              changed: Optional[NDArray[np.int64]] = None) -> List[Tuple[int, int]]:
        """
        Merge confirmed tracks of one class that became compatible and rarely met.

        Two confirmed landmarks this tracker allocated, of the same class, whose means
        pass the gate ``d2 <= chi2_threshold(2, association_gate_probability)`` with
        ``S = P_a + P_b`` (``compatible_pairs``) and whose sightings favour one landmark
        (``one_landmark``: never, or seldom for how often they were seen and the
        detection probability, both in one message) are one landmark: the one
        with fewer observations is fused into the other and taken out of the map
        (``LandmarkMap.merge``: with split CI its per-source sums are added to the
        other's, as if its rows had gone there) and its ID recorded in
        ``merged_into``. Before that, with ``delete_confirmed_tracks``, the owned
        confirmed tracks whose score fell from its peak by the confirmation threshold
        are deleted (``delete_confirmed``).

        Parameters
        ----------
        landmark_map : LandmarkMap
            The map.
        counts : collections.Counter
            Counters where ``merged`` is counted.
        changed : ndarray of int, shape (C,), optional
            Only pairs with one of these landmarks are checked (the fuser passes what
            an update changed: a pair becomes compatible only when one of its two
            changes); all pairs by default.

        Returns
        -------
        list of (int, int)
            ``(retired ID, kept ID)`` pairs; a deleted track is ``(ID, ID)``, first.

        """
        deleted = (self.delete_confirmed(landmark_map, counts)
                   if self.config.delete_confirmed_tracks else [])
        snapshot = landmark_map.snapshot()
        ids, observations = snapshot.ids, snapshot.observations
        merged, retired = [], set()
        for a, b, _ in self.compatible_pairs(snapshot, changed):
            if a in retired or b in retired:
                continue
            pair = (int(ids[a]), int(ids[b]))
            if not self.one_landmark(*pair):
                continue
            keep, drop = (a, b) if observations[a] >= observations[b] else (b, a)
            if not landmark_map.merge(int(ids[keep]), int(ids[drop])):
                continue
            retired.add(drop)
            merged.append((int(ids[drop]), int(ids[keep])))
            self.merged_into[int(ids[drop])] = int(ids[keep])
            self.owned.discard(int(ids[drop]))
            self.scores.pop(int(ids[drop]), None)
            self._merge_counts(int(ids[keep]), int(ids[drop]))
        if merged:
            counts['merged'] += len(merged)
            self.dirty = True
        return [(i, i) for i in deleted] + merged

    def compatible_pairs(self, snapshot: MapSnapshot,
                         changed: Optional[NDArray[np.int64]] = None
                         ) -> List[Tuple[int, int, float]]:
        """
        Return the pairs of owned confirmed landmarks of one class that may be one landmark.

        The difference of two estimates of one landmark has the covariance
        ``P_a + P_b - C - C^T``, with ``C`` the cross-covariance their dependent parts
        (shared pose and bias errors) leave unknown. For every ``omega`` in (0, 1),
        ``S(omega) = P_ind_a + P_ind_b + P_dep_a / omega + P_dep_b / (1 - omega)``
        bounds it whatever that correlation (the covariance-intersection inequality;
        ``P_ind = P - P_dep``), so the difference's squared Mahalanobis distance is at
        least ``d2 = max over omega of d^T S(omega)^-1 d``
        (``gating.difference_mahalanobis_sq``). A
        pair is compatible when ``d2 <= chi2_threshold(2, association_gate_probability)``:
        two estimates of one landmark fail it at most at the gate's rate, whatever
        their correlation. Without dependent parts ``d2`` is the distance on
        ``P_a + P_b``. Candidates are searched on ``P_a + P_b`` with the threshold
        doubled (``S(1/2) <= 2 (P_a + P_b)``, so no compatible pair is missed).

        Parameters
        ----------
        snapshot : MapSnapshot
            The confirmed map.
        changed : ndarray of int, shape (C,), optional
            Only pairs with one of these landmarks; all pairs by default.

        Returns
        -------
        list of (int, int, float)
            ``(a, b, d2)``: rows ``a < b`` of ``snapshot`` and ``d2``, at most the
            gate; sorted by rows.

        """
        owned = np.fromiter(self.owned, np.int64, len(self.owned))
        mine = np.flatnonzero(np.isin(snapshot.ids, owned))
        if len(mine) < 2:
            return []
        ids, m, P = snapshot.ids[mine], snapshot.m[mine], snapshot.P[mine]
        P_dep = snapshot.P_dep[mine]
        queries = np.arange(len(ids))
        if changed is not None:
            queries = np.flatnonzero(np.isin(ids, np.asarray(changed, np.int64)))
            if not len(queries):
                return []
        index = LandmarkIndex(m, P, self.class_of(ids))
        # chi2 with 2 dof: threshold -2 ln(1 - p), doubled at p' = 1 - (1 - p)^2.
        wide = 1.0 - (1.0 - self.config.association_gate_probability) ** 2
        cands = candidates(index, m[queries], P[queries], self.class_of(ids[queries]), wide)
        threshold = chi2_threshold(2, self.config.association_gate_probability)
        rows, others = queries[cands.rows], cands.landmarks
        distinct = rows != others
        rows, others = rows[distinct], others[distinct]
        d2 = difference_mahalanobis_sq(m[rows] - m[others], P[rows] - P_dep[rows],
                                       P_dep[rows], P[others] - P_dep[others], P_dep[others])
        pairs: Dict[Tuple[int, int], float] = {}
        for a, b, value in zip(rows.tolist(), others.tolist(), d2.tolist()):
            if value <= threshold:
                key = (min(a, b), max(a, b))
                pairs[key] = min(value, pairs.get(key, value))
        return [(int(mine[a]), int(mine[b]), d2) for (a, b), d2 in sorted(pairs.items())]

    def one_landmark(self, a: int, b: int) -> bool:
        """
        Decide whether two compatible owned tracks are one landmark, from their sightings.

        ``k`` messages gave rows to both; since their first meeting ``n = k + apart``
        gave a row to either. ``track_score.one_landmark_by_sightings`` decides, with
        ``p_D`` = ``detection_probability`` when set, else the team's online estimate
        (``track_score.team_detection_probability``), the rate ``merge_together_same``
        and the confirmation threshold of the track score.
        """
        k = self.together.get(a, {}).get(b, 0)
        p_D = self.config.detection_probability or team_detection_probability(
            self.statistics.values())
        confirm, _ = sprt_thresholds(self.config.false_track_probability,
                                     self.config.lost_track_probability)
        return one_landmark_by_sightings(k, k + self.apart.get(a, {}).get(b, 0), p_D,
                                         self.config.merge_together_same,
                                         1.0 - self.config.association_gate_probability,
                                         confirm)

    def to_dict(self) -> Dict[str, Any]:
        """Return what a restart needs to resume the tracks (``track_file.tracks_to_dict``)."""
        return track_file.tracks_to_dict(self)

    def restore(self, document: Optional[Dict[str, Any]], landmark_map: LandmarkMap) -> int:
        """
        Resume the tracks of a map file (``to_dict``); return the tentative tracks resumed.

        The rows of each released tentative track go through ``LandmarkMap.update``
        again, so the map buffers them as it did before the restart; the others stay
        with their tracks. A file without tracks resumes none; one without statistics
        (or scores) starts them afresh (``track_file.parse_tracks``).

        Raises
        ------
        ValueError
            If the section is malformed (a field missing or of the wrong type, an ID
            outside 0..2^32 - 2).

        """
        if document is None:
            return 0
        section = track_file.parse_tracks(document)
        tracks = section.tracks
        rows, self.rejected_tracks = track_file.checked_rows(tracks, section.rows)
        rows = sorted((r for r in rows if tracks[r[0]].released), key=lambda row: row[5])
        if rows:
            landmark_map.update(np.array([r[0] for r in rows], np.int64),
                                np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                                np.array([r[3] for r in rows]), np.array([r[4] for r in rows]),
                                np.array([r[5] for r in rows], np.int64))
        self.owned, self.merged_into = section.owned | set(tracks), section.merged_into
        self.sightings, self.together = section.sightings, section.together
        self.apart = section.apart
        self.tentative, self.now_ns = tracks, section.now_ns
        self.statistics = section.statistics
        for landmark_id, track in tracks.items():
            if track.landmark_class:
                self.classes[landmark_id] = track.landmark_class
        self.dirty = True
        return len(tracks)

    def resolve(self, landmark_id: int) -> int:
        """Return the ID a landmark ended up as, following merges."""
        while landmark_id in self.merged_into:
            landmark_id = self.merged_into[landmark_id]
        return landmark_id

    def _pair(self, index: LandmarkIndex, z: NDArray[np.float64], R: NDArray[np.float64],
              classes: NDArray[np.int64], scan: Optional[Scan],
              counts: Counter[str]) -> Tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Return each row's landmark in ``index`` (-1 none) and the rows skipped."""
        cands = candidates(index, z, R, classes, self.config.association_gate_probability)
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
                                          scan.sensor_xy, scan.range_scale_variance)
                except ValueError:
                    C_z = None
            if C_z is None:
                C_z = scan_covariance(z, R, np.zeros(2), np.zeros((3, 3)))
            result = jcbb(cands, index, z, C_z)
            if result.fallback:
                counts['jcbb_fallback'] += 1
        paired = np.array(result.assignment, np.int64)
        ambiguous = np.zeros(len(z), bool)
        open_rows = _open_ambiguity(cands, result)
        if len(open_rows):
            counts['ambiguous'] += len(open_rows)
            if self.config.ambiguous_rows == 'skip':
                paired[open_rows] = -1
                ambiguous[open_rows] = True
        return paired, ambiguous

    def after_update(self, result: UpdateResult,
                     counts_of: Dict[str, Counter[str]]) -> None:
        """Note the tracks an update confirmed; mark the index stale if the map changed."""
        for landmark_id in result.confirmed:
            track = self.tentative.pop(landmark_id, None)
            if track is not None:
                counts_of[track.source]['confirmed'] += 1
                self.stats(track.source).confirmed += 1
                for name, count in track.hits.items():
                    self.stats(name).clutter_rows -= count
        if result.changed:
            self.dirty = True

    def expire(self, landmark_map: LandmarkMap, now_ns: int,
               counts_of: Dict[str, Counter[str]]) -> List[int]:
        """
        Delete the tentative tracks older than ``tentative_timeout_s``; return their IDs.

        Parameters
        ----------
        landmark_map : LandmarkMap
            Where their buffered rows are forgotten.
        now_ns : int
            The newest observation stamp fused [ns] (the clock ``now_ns`` moves to it
            if it is newer; the clock is what counts).
        counts_of : dict of str to collections.Counter
            Counters by source; ``deleted`` is counted on the source that started a track.

        Returns
        -------
        list of int

        """
        now_ns = self.advance(now_ns)
        timeout_ns = self.config.tentative_timeout_s * 1e9
        if not self.tentative or timeout_ns <= 0.0:
            return []
        old = [landmark_id for landmark_id, track in self.tentative.items()
               if now_ns - track.first_ns > timeout_ns]
        if old:
            self._delete(old, landmark_map, counts_of)
        return old


def _open_ambiguity(cands: Candidates, result: Association) -> NDArray[np.intp]:
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
