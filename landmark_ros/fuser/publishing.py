"""
What the fuser publishes and when.

The updates and the full map on one timer (``PublicationSchedule``), and the rows that
announce removed (merged) landmarks (``removal_rows``).
"""

import math
from typing import Sequence, Tuple

from landmark_ros.fusion.landmark_map import LandmarkMap, MapSnapshot
import numpy as np
from numpy.typing import NDArray


class PublicationSchedule:
    """
    One timer for the fuser's map outputs, so that both read the map after one fold.

    Reading the map folds every landmark whose sums changed since it was last folded
    (``LandmarkMap.update(..., settle=False)``); with a timer per output, the full map
    and the updates each paid that fold, about once per landmark per tick at high
    rates. Here one timer ticks at the faster of the two rates; the updates go out
    every ``updates_every``-th tick and the full map every ``map_every``-th tick (the
    updates first: the map then finds nothing left to fold). Each output keeps at
    most its configured rate: with the defaults (5 and 10 Hz) the tick is 10 Hz and
    the full map goes with every second one.

    Parameters
    ----------
    publish_rate_hz : float
        Most full maps per second [Hz], > 0.
    updates_rate_hz : float
        Most update messages per second [Hz], > 0.

    Raises
    ------
    ValueError
        If a rate is not positive.

    """

    def __init__(self, publish_rate_hz: float, updates_rate_hz: float) -> None:
        if not (publish_rate_hz > 0.0 and updates_rate_hz > 0.0):
            raise ValueError('the publication rates must be positive, got '
                             f'{publish_rate_hz!r} and {updates_rate_hz!r}')
        rate = max(publish_rate_hz, updates_rate_hz)
        self.period_s = 1.0 / rate
        """Tick period [s]."""
        self.updates_every = _every(rate, updates_rate_hz)
        self.map_every = _every(rate, publish_rate_hz)
        self.ticks = 0

    @property
    def updates_period_s(self) -> float:
        """Return the period of the updates [s] (at least 1 / ``updates_rate_hz``)."""
        return self.updates_every * self.period_s

    @property
    def map_period_s(self) -> float:
        """Return the period of the full map [s] (at least 1 / ``publish_rate_hz``)."""
        return self.map_every * self.period_s

    def tick(self) -> Tuple[bool, bool]:
        """Count one tick; return whether the updates and whether the full map are due."""
        self.ticks += 1
        return self.ticks % self.updates_every == 0, self.ticks % self.map_every == 0


def _every(rate: float, wanted: float) -> int:
    """Return the fewest ticks at ``rate`` between two outputs of at most ``wanted`` per s."""
    # The tolerance keeps exact ratios (10 / 5) from rounding up.
    return max(1, math.ceil(rate / wanted * (1.0 - 1e-12)))


def removal_rows(landmark_map: LandmarkMap, removed: Sequence[tuple],
                 deleted: Sequence[tuple] = ()) -> Tuple[MapSnapshot, NDArray[np.int64]]:
    """
    Return the rows that announce removed landmarks, and what each went into.

    Parameters
    ----------
    landmark_map : LandmarkMap
        The fuser's map.
    removed : sequence of (int, int)
        ``Fuser.take_removed()``: ``(ID, ID)`` for a deleted track.
    deleted : sequence of (int, ndarray, ndarray, ndarray)
        ``Tracker.deleted``: ``(ID, m, P, P_dep)``, the last estimate of each deleted
        track.

    Returns
    -------
    rows : MapSnapshot
        Per removed landmark whose landmark is confirmed (or that was deleted), in
        order: its ID, the estimate of the landmark it went into (a deleted one: its
        own last estimate), 0 observations.
    merged_into : ndarray of int64, shape (K,)
        The landmark each went into; its own ID for a deleted one.

    """
    kept = landmark_map.snapshot(np.array([keep for _, keep in removed], np.int64))
    where = {landmark_id: (kept.m[k], kept.P[k], kept.P_dep[k])
             for k, landmark_id in enumerate(kept.ids.tolist())}
    gone = {entry[0]: tuple(entry[1:]) for entry in deleted}
    pairs = [(drop, keep) for drop, keep in removed
             if keep in where or (drop == keep and drop in gone)]
    estimates = [where[keep] if keep in where else gone[keep] for _, keep in pairs]
    merged_into = np.array([keep for _, keep in pairs], np.int64)
    return type(kept)(np.array([drop for drop, _ in pairs], np.int64),
                      np.array([e[0] for e in estimates]).reshape(-1, 2),
                      np.array([e[1] for e in estimates]).reshape(-1, 2, 2),
                      np.array([e[2] for e in estimates]).reshape(-1, 2, 2),
                      np.zeros(len(pairs), np.int64)), merged_into
