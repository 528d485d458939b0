"""
The score step of the ``Tracker`` (``fuser.tracks``): hits, misses, release, deletion.

After each message's association, ``ScoredTracks.screen`` scores the tentative tracks
(``fuser.track_score``), keeps the rows of those not yet confirmed by their score,
releases (sends to the map) the rows of those that reach the confirmation threshold
and deletes those that fall to the deletion threshold.

Confirmed tracks (those the tracker allocated) go on scoring hits and misses the same
way. Their score only grows while the landmark is there; the log-likelihood ratio of
"the landmark has been gone since message j" against "it is there" is ``L_j - L``, so
the largest of them is the drop of the score from its peak, ``peak - L`` (Page's test
on the track score; Blackman and Popoli 1999, sec. 6.2 delete a confirmed track by
its fall from the maximum). With ``delete_confirmed_tracks`` (off by default:
misses correlated in time, see docs/association.md) a confirmed track is deleted when the drop
reaches the confirmation threshold ``ln((1 - beta) / alpha)``: taking a landmark out of the map
needs as much evidence against it as putting it in needed for it. The landmark leaves the
map (``LandmarkMap.retire``), ``deleted`` is counted on the message's source, and the
fuser announces it as a removal whose ``merged_into`` is the landmark's own ID, with
its last estimate. The score and peak start at 0 when a confirmed track is first in
view (after its confirmation or a restart: they are not saved).
"""

from collections import Counter
from typing import Any, Dict, List, Set, Tuple

from landmark_ros.core.gating import chi2_threshold
from landmark_ros.fuser.sources import Queued
from landmark_ros.fuser.track_file import track_estimate
from landmark_ros.fuser.track_score import (bearings_from, hit_increments, miss_increment,
                                            SourceStatistics, sprt_thresholds)
from landmark_ros.fusion.landmark_map import LandmarkMap
import numpy as np
from numpy.typing import NDArray

TRACK_ROWS_KEPT = 32
"""Rows of a tentative track kept (the newest): what the map gets when the score confirms
it, and what the map file keeps."""


class ScoredTracks:
    """The score step of ``fuser.tracks.Tracker`` (a mixin: it uses the tracker's state)."""

    config: Any
    tentative: Dict[int, Any]
    statistics: Dict[str, SourceStatistics]
    owned: Set[int]
    dirty: bool
    _indices: List[Any]
    scores: Dict[int, List[float]]
    deleted: List[Tuple[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]

    def _forget_counts(self, landmark_id: int) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def stats(self, source: str) -> SourceStatistics:
        """Return the estimates of ``source`` (``fuser.track_score``), new ones if none."""
        return self.statistics.setdefault(source, SourceStatistics())

    def screen(self, landmark_map: LandmarkMap, item: Queued, unlabelled: NDArray[np.bool_],
               source: str, counts_of: Dict[str, Counter[str]]) -> List[Tuple[Queued, str]]:
        """
        Score the tracks after one message's association; return what goes to the map.

        The tentative tracks that got rows score hits, those in the source's view that
        got none misses (``fuser.track_score``); the source's estimates take the
        message in. A track whose score reaches the confirmation threshold is released
        (its rows go to the map, which confirms it), one whose score falls to the
        deletion threshold is deleted (``deleted``). Rows of tracks not released stay
        here (``Track.rows``).

        Parameters
        ----------
        landmark_map : LandmarkMap
            The map as the message's association saw it.
        item : Queued
            The message with the IDs its rows got (rows dropped as ambiguous removed).
        unlabelled : ndarray of bool, shape (N,)
            Which of its rows came without an ID.
        source : str
            The message's source.
        counts_of : dict of str to collections.Counter
            Counters by source.

        Returns
        -------
        list of (Queued, str)
            The rows of released tracks (one entry per row, in their order), then the
            message's rows for the map, with the source of each entry.

        """
        stats, ids = self.stats(source), item.ids
        confirmed_ids = self._indices[0][1] if self._indices else np.empty(0, np.int64)
        paired = np.isin(ids, confirmed_ids) & unlabelled
        mine = np.array([i in self.tentative for i in ids.tolist()], bool)
        touched = set(ids[mine].tolist())
        if item.scan is not None:
            self._view(stats, item, unlabelled, paired, touched)
        for k in np.flatnonzero(mine).tolist():
            track = self.tentative[int(ids[k])]
            row = (item.m[k].copy(), item.P[k].copy(), item.P_dep[k].copy(), source,
                   int(item.stamp_ns))
            if track.rows:
                track.score += float(hit_increments(
                    item.m[k:k + 1], track.m[None], (track.P + item.P[k])[None],
                    stats.detection_probability, stats.clutter_density)[0])
            track.rows.append(row)
            del track.rows[:-TRACK_ROWS_KEPT]
            track.m, track.P = track_estimate(track.rows)
            track.hits[source] = track.hits.get(source, 0) + 1
            self.dirty = True
        # Rows of tracks released before: to the map now; of those released now: with
        # their track's rows, in order.
        keep = ~mine | np.array([i in self.tentative and self.tentative[i].released
                                 for i in ids.tolist()], bool)
        released = self._decide(landmark_map, touched, counts_of)
        rows = [(Queued(item.sequence, np.array([i], np.int64), m[None], P[None], P_dep[None],
                        stamp_ns), name)
                for i, (m, P, P_dep, name, stamp_ns) in released]
        if keep.any():
            rows.append((Queued(item.sequence, ids[keep], item.m[keep], item.P[keep],
                                item.P_dep[keep], item.stamp_ns, None, item.scan, False),
                         source))
        return rows

    def _view(self, stats: SourceStatistics, item: Queued, unlabelled: NDArray[np.bool_],
              paired: NDArray[np.bool_], touched: Set[int]) -> None:
        """
        Take one message's view in: range, clutter, detections; score the misses.

        A landmark or track in view (``fuser.track_score``) that got no row is missed
        only if no row of the message lies in its gate (a row another landmark took
        might have been its): the rest neither hit nor miss.
        """
        assert item.scan is not None
        robot_xy = np.asarray(item.scan.robot_xy, np.float64)
        heading = item.scan.heading
        z, R = item.m[unlabelled], item.P[unlabelled]
        stats.see(np.linalg.norm(z - robot_xy, axis=1), paired[unlabelled],
                  None if heading is None else bearings_from(z - robot_xy, heading))
        threshold = chi2_threshold(2, self.config.association_gate_probability)
        if self._indices and len(self._indices[0][0]):
            index, index_ids = self._indices[0]
            near = np.flatnonzero(stats.in_view(index.m_map, robot_xy, heading))
            hit = np.isin(index_ids[near], item.ids[paired])
            gated = _gated(index.m_map[near], index.P_map[near], z, R, threshold)
            stats.expected += len(near)
            stats.detected += int(hit.sum())
            self._score_confirmed(stats, item, paired, near, (hit, gated))
        stats.clutter_rows += int((unlabelled & ~paired).sum())
        stats.area += stats.view_area(heading)
        ids = [i for i, t in self.tentative.items() if i not in touched and t.rows]
        if not ids:
            return
        m = np.array([self.tentative[i].m for i in ids])
        P = np.array([self.tentative[i].P for i in ids])
        missed = stats.in_view(m, robot_xy, heading) & ~_gated(m, P, z, R, threshold)
        miss = miss_increment(stats.detection_probability)
        for k in np.flatnonzero(missed).tolist():
            self.tentative[ids[k]].score += miss
            touched.add(ids[k])

    def _score_confirmed(self, stats: SourceStatistics, item: Queued,
                         paired: NDArray[np.bool_], near: NDArray[np.intp],
                         seen: Tuple[NDArray[np.bool_], NDArray[np.bool_]]) -> None:
        """Score the owned confirmed tracks in view (``near``): hits, misses (module notes)."""
        hit, gated = seen
        index, index_ids = self._indices[0]
        miss = miss_increment(stats.detection_probability)
        for j in np.flatnonzero(np.isin(index_ids[near], list(self.owned))).tolist():
            row, landmark_id = int(near[j]), int(index_ids[near[j]])
            score = self.scores.setdefault(landmark_id, [0.0, 0.0])
            if hit[j]:
                k = int(np.flatnonzero((item.ids == landmark_id) & paired)[0])
                score[0] += float(hit_increments(
                    item.m[k:k + 1], index.m_map[row][None], (index.P_map[row] + item.P[k])[None],
                    stats.detection_probability, stats.clutter_density)[0])
                score[1] = max(score[1], score[0])
            elif not gated[j]:
                score[0] += miss

    def delete_confirmed(self, landmark_map: LandmarkMap, counts: Counter[str]) -> List[int]:
        """
        Delete the owned confirmed tracks whose score fell from its peak by the threshold.

        Returns
        -------
        list of int
            Their IDs; ``deleted`` keeps ``(ID, m, P, P_dep)`` of each, its last estimate.

        """
        confirm, _ = sprt_thresholds(self.config.false_track_probability,
                                     self.config.lost_track_probability)
        old = sorted(i for i, (score, peak) in self.scores.items() if peak - score >= confirm)
        if not old:
            return []
        snapshot = landmark_map.snapshot(np.array(old, np.int64))
        for k, landmark_id in enumerate(snapshot.ids.tolist()):
            self.deleted.append((landmark_id, snapshot.m[k], snapshot.P[k], snapshot.P_dep[k]))
        landmark_map.retire(np.array(old, np.int64))
        for landmark_id in old:
            del self.scores[landmark_id]
            self.owned.discard(landmark_id)
            self._forget_counts(landmark_id)
        counts['deleted'] += len(old)
        self.dirty = True
        return old

    def _decide(self, landmark_map: LandmarkMap, touched: Set[int],
                counts_of: Dict[str, Counter[str]]) -> List[tuple]:
        """Release or delete the touched tracks by their scores; return the rows released."""
        confirm, delete = sprt_thresholds(self.config.false_track_probability,
                                          self.config.lost_track_probability)
        released: List[tuple] = []
        for landmark_id in sorted(touched):
            track = self.tentative.get(landmark_id)
            if track is None:
                continue
            if not track.released and track.score >= confirm:
                track.released = True
                released += [(landmark_id, row) for row in track.rows]
            elif not track.released and track.score <= delete:
                self._delete([landmark_id], landmark_map, counts_of)
        return released

    def _delete(self, old: List[int], landmark_map: LandmarkMap,
                counts_of: Dict[str, Counter[str]]) -> None:
        """Delete tentative tracks: their rows in the map are forgotten, counted."""
        landmark_map.forget(np.array(old, np.int64))
        for landmark_id in old:
            track = self.tentative.pop(landmark_id)
            counts = counts_of.get(track.source)
            if counts is not None:
                counts['deleted'] += 1
            self.stats(track.source).deleted += 1
            self.owned.discard(landmark_id)
            self._forget_counts(landmark_id)
        self.dirty = True


def _gated(m: NDArray[np.float64], P: NDArray[np.float64], z: NDArray[np.float64],
           R: NDArray[np.float64], threshold: float) -> NDArray[np.bool_]:
    """Return, per landmark ``m`` (K, 2), ``P`` (K, 2, 2), whether a row lies in its gate."""
    if not len(m) or not len(z):
        return np.zeros(len(m), bool)
    nu = z[None, :, :] - m[:, None, :]
    S = P[:, None] + R[None, :]
    d2 = np.einsum('kni,kni->kn', nu, np.linalg.solve(S, nu[..., None])[..., 0])
    return (d2 <= threshold).any(axis=1)
