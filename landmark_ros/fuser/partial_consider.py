"""
Each robot's sensor bias as a consider state of the landmarks placed from views (ROS-free).

With split CI and ``source_correlation: independent``, a view's sensor bias
(``R_bias``: ``range_bias_stddev``, ``bearing_bias_stddev``) is the same in every view
of that robot and kind. Split CI takes it as of unknown correlation with the
landmark's error at every update; seen from every side of a landmark, where a range
bias mostly cancels, the landmark keeps it in full and ends under-confident
(``test/core/test_partial_consider.py``). Here, for each landmark, the
cross-covariance ``c`` of its error with each (robot, kind) bias is carried from the
placement on (``core.partial.update_consider``), so a bias counts once. Only range
views use it (``CONSIDERED_KINDS``); the cross-covariances of every kind start at the
placement, and a bearing view's update (split CI) ends them.

Bookkeeping. At the placement, ``initialise`` gives ``P_dep = B D B^T`` with ``B`` the
map from the views to the landmark and ``D`` the views' dependent errors; a group of
views sharing a bias with loadings ``l`` (``sqrt(R_bias)``) gives ``c = B l``, and the
part of ``P_dep`` the biases explain is ``sum c c^T``; the rest (the pose errors) is
what split CI keeps handling, split by robot (``partial_sources.SourceLedger``). The
map's ``P_dep`` always holds both, so anything else that reads or changes the
landmark (range-bearing rows, the map file) sees the biases as dependent, as before.
A landmark whose estimate changed outside these updates (a range-bearing row, a
reload) loses its cross-covariances: its views then take the bias as of unknown
correlation again.
"""

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from landmark_ros.core.partial import Initialisation, linearise, RANGE, Views
import numpy as np
from numpy.typing import NDArray

CONSIDERED_KINDS = (RANGE,)
"""View kinds whose bias is a consider state. Bearing views keep split CI on theirs: a
robot's bearing error is more than a constant bias with the calibrated spread (on MRCLAM
dataset 6 robot 4 sees every landmark 7 to 21 mrad off against 5.4 mrad), and with it
as a consider state the bearing-only replay is over-confident (docs/sensors.md)."""

Key = Tuple[str, int]
"""A bias: the source (robot) and the view kind."""

Estimate = Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
"""A landmark's ``m`` (2,), ``P`` and ``P_dep`` (2, 2), as the map holds it."""


@dataclass(frozen=True)
class Crosses:
    """The cross-covariances of one landmark's error with the biases [m]."""

    c: Dict[Key, NDArray[np.float64]]
    estimate: Estimate
    """The estimate they belong to: the map's, as the last update set it."""

    def bias_part(self) -> NDArray[np.float64]:
        """Return ``sum c c^T``, the part of the landmark's covariance the biases explain."""
        return sum((np.outer(c, c) for c in self.c.values()), np.zeros((2, 2)))

    def after(self, key: Key, c_key: NDArray[np.float64], L: NDArray[np.float64],
              estimate: Estimate) -> 'Crosses':
        """Return them after an update by a view of bias ``key`` (``I - K H`` = ``L``)."""
        c = {k: L @ value for k, value in self.c.items() if k != key}
        c[key] = np.asarray(c_key, dtype=np.float64)
        return Crosses(c, estimate)


def psd_part(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return the symmetric (2, 2) ``M`` with its negative eigenvalues set to 0."""
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    return (V * np.maximum(w, 0.0)) @ V.T


def _same(a: Estimate, b: Estimate) -> bool:
    return all(np.allclose(x, y, rtol=1e-9, atol=1e-15) for x, y in zip(a, b))


class BiasCrosses:
    """The landmarks' cross-covariances with the (robot, kind) biases of their views."""

    def __init__(self) -> None:
        self._crosses: Dict[int, Crosses] = {}

    def clear(self) -> None:
        """Forget every landmark's cross-covariances."""
        self._crosses.clear()

    def forget(self, landmark_id: int) -> None:
        """Forget one landmark's cross-covariances."""
        self._crosses.pop(int(landmark_id), None)

    def keep(self, landmark_id: int, crosses: Crosses) -> None:
        """Hold ``crosses`` as the landmark's."""
        self._crosses[int(landmark_id)] = crosses

    def current(self, landmark_id: int, estimate: Estimate) -> Optional[Crosses]:
        """Return the landmark's cross-covariances if they belong to ``estimate``, else None."""
        crosses = self._crosses.get(int(landmark_id))
        if crosses is not None and not _same(crosses.estimate, estimate):
            self.forget(landmark_id)
            return None
        return crosses

    @staticmethod
    def placed(views: Views, keys: List[Key], placed: Initialisation,
               estimate: Estimate) -> Crosses:
        """
        Return the cross-covariances of a landmark ``initialise`` placed from ``views``.

        ``keys`` gives each view's bias; ``estimate`` is the map's after the placement.
        ``c = B l`` per bias, ``B = (J^T W J)^-1 J^T W`` the least-squares map of
        ``initialise`` at the solution (``W = 1 / R_eff``).
        """
        lin = linearise(views, placed.m)
        J = lin.J_h_m[:, 0, :]
        JW = J.T / lin.R_eff
        B = np.linalg.solve(JW @ J, JW)
        load = np.sqrt(views.R_bias)
        c: Dict[Key, NDArray[np.float64]] = {}
        for n, key in enumerate(keys):
            c[key] = c.get(key, np.zeros(2)) + B[:, n] * load[n]
        return Crosses(c, estimate)
