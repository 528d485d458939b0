"""
The landmark map with what change detection needs: innovations and a rebuild on demand.

``MovingLandmarkMap`` is a ``LandmarkMap`` (same state, same updates) with two more
methods for ``fuser.change_detection``: ``gate_distances``, the normalised innovation
squared of rows against their landmarks' gate references (what ``update`` gates them
by), and ``rebuild``, a confirmed landmark set again from given observations only (its
post-change rows).
"""

from typing import Sequence

from landmark_ros.core.arrays import mahalanobis_sq_2x2
from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.fusion.records import Observation
from landmark_ros.fusion.source_sums import entries
import numpy as np
from numpy.typing import ArrayLike, NDArray


class MovingLandmarkMap(LandmarkMap):
    """A ``LandmarkMap`` whose landmarks change detection can rebuild (parameters there)."""

    def gate_distances(self, ids: ArrayLike, z: ArrayLike, R: ArrayLike) -> NDArray[np.float64]:
        """
        Return each row's squared Mahalanobis distance to its landmark's gate reference.

        The distance ``update`` would gate the row by now: ``d^T (P_ref + R)^-1 d`` with
        ``d = z - m_ref`` (the normalised innovation squared).

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            Landmark IDs.
        z : ndarray, shape (N, 2)
            Observed positions [m].
        R : ndarray, shape (N, 2, 2)
            Their total covariances [m^2].

        Returns
        -------
        ndarray, shape (N,)
            NaN for IDs that are not confirmed landmarks.

        """
        rows = self._lookup(np.asarray(ids, dtype=np.int64).reshape(-1))
        d2 = np.full(len(rows), np.nan)
        known = rows >= 0
        known[known] = self.confirmed[rows[known]]
        if known.any():
            gate = self.gate[rows[known]]
            d = np.asarray(z, dtype=np.float64).reshape(-1, 2)[known] - gate[:, :2]
            R_entries = entries(np.asarray(R, dtype=np.float64).reshape(-1, 2, 2)[known])
            d2[known] = mahalanobis_sq_2x2(d[:, 0], d[:, 1], *(
                gate[:, 2 + k] + R_entries[k] for k in range(3)))
        return d2

    def rebuild(self, landmark_id: int, observations: Sequence[Observation]) -> bool:
        """
        Set a confirmed landmark from ``observations`` alone (it moved); return whether it was.

        From their largest agreeing subset (``records.agreeing``) when it holds at least
        ``min_observations``, by the fusion method's ``start`` (split CI: the per-source
        sums restart from those rows), as the rebuild after ``max_consecutive_rejections``.
        False (the map unchanged) for an ID that is not a confirmed landmark or rows that
        do not agree.
        """
        row = int(self._lookup(np.array([landmark_id], np.int64))[0])
        if row < 0 or not self.confirmed[row]:
            return False
        return bool(self._rebuild(row, list(observations)))
