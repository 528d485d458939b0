"""
The tentative tracks in the map file: their record, writing and checked reading (ROS-free).

``Tracker.to_dict`` and ``Tracker.restore`` (``fuser.tracks``) use these functions:
``tracks_to_dict`` writes the ``tracks`` section, ``parse_tracks`` reads it back with
every field checked, and ``checked_rows`` drops the tracks whose rows the live row
checks refuse.
"""

from dataclasses import dataclass, field
from typing import Any, Dict, List, NamedTuple, Optional, Set, Tuple, TYPE_CHECKING

from landmark_ros.fuser.track_score import SourceStatistics
from landmark_ros.pipeline.rows import landmark_row_problems, MAX_LABEL_ID
import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover
    from landmark_ros.fuser.tracks import Tracker


@dataclass
class Track:
    """A tentative track: its estimate (mean [m], covariance [m^2]), rows and score."""

    m: NDArray[np.float64]
    P: NDArray[np.float64]
    landmark_class: int
    first_ns: int
    source: str
    rows: List[tuple] = field(default_factory=list)
    """``(m, P, P_dep, source, stamp_ns)`` of the rows it got (the newest
    ``TRACK_ROWS_KEPT``), saved in the map file; the map gets them once released."""
    score: float = 0.0
    """Log-likelihood ratio landmark / clutter (``fuser.track_score``)."""
    released: bool = False
    """Whether the score confirmed it: its rows went to the map (which confirms it once
    ``min_observations`` of them agree)."""
    hits: Dict[str, int] = field(default_factory=dict)
    """Rows it got, by source (taken off the clutter count when it is confirmed)."""


def track_estimate(rows: List[tuple]) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the mean (2,) [m] and covariance (2, 2) [m^2] of a track's rows.

    The independent parts ``P - P_dep`` are fused as independent (information sum);
    the dependent parts (pose error, shared by the rows of one robot) are taken as
    fully correlated: their mean is added, which never understates the covariance.
    """
    P = np.array([r[1] for r in rows])
    P_dep = np.array([r[2] for r in rows])
    P_ind = P - P_dep + 1e-12 * np.eye(2)
    Y = np.linalg.inv(P_ind)
    P_fused = np.linalg.inv(Y.sum(axis=0))
    m = P_fused @ np.einsum('nij,nj->i', Y, np.array([r[0] for r in rows]))
    P_out = P_fused + P_dep.mean(axis=0)
    return m, 0.5 * (P_out + P_out.T)


class TrackSection(NamedTuple):
    """The ``tracks`` section of a map file, checked (``parse_tracks``)."""

    owned: Set[int]
    sightings: Dict[int, int]
    together: Dict[int, Dict[int, int]]
    apart: Dict[int, Dict[int, int]]
    merged_into: Dict[int, int]
    now_ns: Optional[int]
    tracks: Dict[int, Track]
    rows: List[tuple]
    """``(track ID, m, P, P_dep, source, stamp_ns)`` of every row of the tracks."""
    statistics: Dict[str, SourceStatistics]


def tracks_to_dict(tracker: 'Tracker') -> Dict[str, Any]:
    """
    Return what a restart needs to resume the tracks, as plain JSON data.

    ``tentative`` (per track: ``id``, ``class``, ``first_stamp_ns``, ``source`` and
    its ``rows``, each ``mean``, ``covariance``, ``covariance_dependent``,
    ``source``, ``stamp_ns``), ``owned`` (the IDs this tracker allocated that are
    still landmarks or tracks), ``sightings`` (``[id, messages]`` for each of them
    a message saw), ``together`` (``[a, b, messages]``, ``a < b``, for each pair of
    them a message saw together), ``apart`` (``[a, b, messages]``, ``a < b``: the
    messages after their first meeting that saw one of the two), ``merged_into``
    (``[retired, kept]`` pairs) and
    ``now_ns`` (the expiry clock, or null); per track also its ``score``, whether it
    was ``released`` and its ``hits`` by source, and ``statistics``: per source, the
    estimates of ``fuser.track_score.SourceStatistics``.
    """
    return {
        'tentative': [{
            'id': int(landmark_id), 'class': int(track.landmark_class),
            'first_stamp_ns': int(track.first_ns), 'source': track.source,
            'score': float(track.score), 'released': bool(track.released),
            'hits': {str(k): int(v) for k, v in sorted(track.hits.items())},
            'rows': [{'mean': m.tolist(), 'covariance': P.tolist(),
                      'covariance_dependent': P_dep.tolist(), 'source': source,
                      'stamp_ns': int(stamp)}
                     for m, P, P_dep, source, stamp in track.rows]}
            for landmark_id, track in sorted(tracker.tentative.items())],
        'owned': sorted(int(i) for i in tracker.owned),
        'sightings': sorted([int(a), int(n)] for a, n in tracker.sightings.items()),
        'together': sorted([int(a), int(b), int(k)] for a, partners in tracker.together.items()
                           for b, k in partners.items() if a < b),
        'apart': sorted([int(a), int(b), int(n)] for a, partners in tracker.apart.items()
                        for b, n in partners.items() if a < b),
        'merged_into': sorted([int(a), int(b)] for a, b in tracker.merged_into.items()),
        'now_ns': None if tracker.now_ns is None else int(tracker.now_ns),
        'statistics': {name: stats.to_dict()
                       for name, stats in sorted(tracker.statistics.items())}}


def _ident(value: Any) -> int:
    """Return ``value`` if it is a landmark ID; raise ValueError otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not (
            0 <= value <= MAX_LABEL_ID):
        raise ValueError(f'{value!r} is not a landmark ID')
    return value


def _count(value: Any) -> int:
    """Return ``value`` if it is a count; raise ValueError otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f'{value!r} is not a count')
    return value


def parse_tracks(document: Dict[str, Any]) -> TrackSection:
    """
    Read the ``tracks`` section of a map file (``tracks_to_dict``), every field checked.

    Raises
    ------
    ValueError
        If the section is malformed (a field missing or of the wrong type, an ID
        outside 0..2^32 - 2).

    """
    ident, count = _ident, _count
    try:
        owned = {ident(i) for i in document.get('owned', [])}
        sightings = {ident(a): count(n) for a, n in document.get('sightings', [])}
        together: Dict[int, Dict[int, int]] = {}
        for entry in document.get('together', []):
            # [a, b, messages]; an older file's [a, b] counts once.
            a, b, k = (*entry, 1) if len(entry) == 2 else entry
            a, b, k = ident(a), ident(b), count(k)
            together.setdefault(a, {})[b] = together.setdefault(b, {})[a] = k
        apart: Dict[int, Dict[int, int]] = {}
        for a, b, n in document.get('apart', []):
            a, b, n = ident(a), ident(b), count(n)
            apart.setdefault(a, {})[b] = apart.setdefault(b, {})[a] = n
        merged = {ident(a): ident(b) for a, b in document.get('merged_into', [])}
        now_ns = document.get('now_ns')
        if now_ns is not None and (isinstance(now_ns, bool) or not isinstance(now_ns, int)):
            raise ValueError(f'now_ns {now_ns!r} is not an integer')
        tracks, rows = {}, []
        for entry in document.get('tentative', []):
            landmark_id = ident(entry['id'])
            track_rows = [(np.array(r['mean'], np.float64).reshape(2),
                           np.array(r['covariance'], np.float64).reshape(2, 2),
                           np.array(r['covariance_dependent'], np.float64).reshape(2, 2),
                           str(r['source']), int(r['stamp_ns'])) for r in entry['rows']]
            if not track_rows:
                raise ValueError(f'tentative track {landmark_id} has no row')
            # An older file's tracks have their rows in the map: released, score 0.
            released = entry.get('released', True)
            score = entry.get('score', 0.0)
            if not isinstance(released, bool) or isinstance(score, bool) or not (
                    isinstance(score, (int, float)) and np.isfinite(score)):
                raise ValueError(f'tentative track {landmark_id}: bad score or released')
            tracks[landmark_id] = Track(
                *track_estimate(track_rows), int(entry['class']), int(entry['first_stamp_ns']),
                str(entry['source']), track_rows, float(score), released,
                {str(k): count(v) for k, v in entry.get('hits', {}).items()})
            rows += [(landmark_id, *row) for row in track_rows]
        statistics = {str(name): SourceStatistics.from_dict(values)
                      for name, values in document.get('statistics', {}).items()}
    except (AttributeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f'tracks section: {error}') from error
    return TrackSection(owned, sightings, together, apart, merged, now_ns, tracks, rows,
                        statistics)


def checked_rows(tracks: Dict[int, Any], rows: List[Any]
                 ) -> Tuple[List[Any], List[Tuple[int, List[str]]]]:
    """
    Drop the tentative tracks with a row the live row checks refuse; return the rest.

    The rows of a track go through ``rows.landmark_row_problems``, the check of live
    landmark rows. Returns the rows kept and, per track dropped, ``(track ID,
    reasons)`` (``Tracker.rejected_tracks``).
    """
    rejected: List[Tuple[int, List[str]]] = []
    if not rows:
        return rows, rejected
    valid, _ = landmark_row_problems(
        np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows]),
        np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))
    bad = sorted({rows[k][0] for k in np.flatnonzero(~valid)})
    for landmark_id in bad:
        mine = [r for r in rows if r[0] == landmark_id]
        _, reasons = landmark_row_problems(
            np.array([r[0] for r in mine], np.int64), np.array([r[1] for r in mine]),
            np.array([r[2] for r in mine]), np.array([r[3] for r in mine]))
        rejected.append((landmark_id, sorted(reasons)))
        del tracks[landmark_id]
    return [r for r in rows if r[0] not in bad], rejected
