"""
The landmark map with what change detection needs: innovations and a rebuild on demand.

``MovingLandmarkMap`` is a ``LandmarkMap`` (same state, same updates) with two more
methods for ``fuser.change_detection``: ``confirmed_ids``, which rows' landmarks are
confirmed (the rows the tests take), and ``rebuild``, a confirmed landmark set again
from given observations only (its post-change rows).
"""

from typing import Sequence

from landmark_ros.fusion.landmark_map import LandmarkMap
from landmark_ros.fusion.records import Observation
import numpy as np
from numpy.typing import ArrayLike, NDArray


class MovingLandmarkMap(LandmarkMap):
    """A ``LandmarkMap`` whose landmarks change detection can rebuild (parameters there)."""

    def confirmed_ids(self, ids: ArrayLike) -> NDArray[np.bool_]:
        """
        Return which IDs are confirmed landmarks now.

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            Landmark IDs.

        Returns
        -------
        ndarray of bool, shape (N,)

        """
        rows = self._lookup(np.asarray(ids, dtype=np.int64).reshape(-1))
        known = rows >= 0
        known[known] = self.confirmed[rows[known]]
        return known

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
