"""
Association of sightings without landmark IDs with the localizer's map (ROS-free).

A row of the observer's cloud without an ``id`` (``UNKNOWN_ID``) is paired with a
landmark of the map by the package's association (``landmark_ros.core.association``,
``landmark_ros.core.joint_compatibility``); nothing is re-implemented here.

Symbols
-------
x, P
    Robot pose ``(x, y, theta)`` at the rows' stamp and its covariance, (3,), (3, 3).
z, R
    Range-bearing rows and their noise, (N, 2), (N, 2, 2).
m_obs, P_obs
    The rows placed in the map frame from ``x`` and their covariance, pose term
    included (``core.landmarks.landmark_to_world``), (N, 2), (N, 2, 2).
m_map, P_map
    The map's landmarks, (K, 2), (K, 2, 2).

Gate
----
A pairing (row i, landmark j) is individually compatible when
``d2 = (m_obs_i - m_j)^T (P_obs_i + P_map_j)^-1 (m_obs_i - m_j)`` passes the
chi-square gate with 2 degrees of freedom (``core.association.candidates``). To first
order this is the gate on the innovation of the predicted observation,
``nu = z - h(x, m_j)`` with ``S = J_z_x P J_z_x^T + J_z_m P_map_j J_z_m^T + R``: the
world-frame innovation is ``-J_z_m^-1 nu`` (``J_z_m`` is invertible for a range-bearing
row away from the sensor) and a Mahalanobis distance does not change under an
invertible linear map. ``P_obs_i`` holds the pose term, so the rows of one message are
correlated through the shared pose error: ``jcbb`` takes their joint covariance
(``core.association.scan_covariance``), ``nn`` gates each row alone.

The methods (parameter ``association``):

``nn``
    Each row to its candidate of smallest d2 (``core.association.nearest_neighbour``).
``jcbb``
    The largest jointly compatible hypothesis of the scan
    (``core.joint_compatibility.jcbb``, Neira and Tardos 2001).

A row with more than one candidate whose choice the method did not settle
(``Association.ambiguous``: for ``nn`` every row with two or more candidates, for
``jcbb`` a row that another candidate would also fit jointly) is not used: a wrong
pairing moves the pose by the distance between two landmarks, which no later update
repairs, while a skipped row costs one sighting. With ``take_ambiguous`` (parameter
``association_take_ambiguous``) the method's choice stands: where the pose is known
only to a fraction of the landmark spacing every row has several candidates, and
skipping them all leaves the filter on dead reckoning for good. With ``merge_ambiguous``
(parameter ``association_merge_ambiguous``) such a row is applied once per candidate
and the results combined (``localizer.mixture``, probabilistic data association), with
the probabilities ``association_probabilities``: ``beta_j`` proportional to
``exp(-d2_j / 2) / sqrt(det S_j)`` (Bar-Shalom and Fortmann, "Tracking and Data
Association", 1988, ch. 6; detection certain, no clutter). Candidates close together
(a pair of landmarks a fraction of the pose's spread apart) give nearly one update;
candidates far apart leave the pose spread between them. Partial rows (range-only or
bearing-only) cannot be placed in the map and are not associated.
"""

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from landmark_ros.core.association import (candidates, LandmarkIndex, nearest_neighbour,
                                           scan_covariance)
from landmark_ros.core.joint_compatibility import jcbb
from landmark_ros.core.landmarks import landmark_to_world
from landmark_ros.core.sensors import MIN_RANGE
from landmark_ros.localizer.update import RANGE_BEARING
import numpy as np
from numpy.typing import NDArray

UNKNOWN_ID = 0xFFFFFFFF
"""ID of a row without one (the observer's cloud schema; ``localizer.UNKNOWN_ID``)."""


@dataclass(frozen=True)
class Assigned:
    """What the association made of the rows without ID."""

    landmark: NDArray[np.intp]
    """Per row the map index (into the ``MapAssociation``'s arrays), -1 for none, (N,)."""
    ambiguous: int
    """Rows left out because their choice was not settled."""
    unmatched: int
    """Rows without any compatible landmark (or that could not be placed)."""
    merged: Optional[Dict[int, Tuple[NDArray[np.intp], NDArray[np.float64]]]] = None
    """With ``merge_ambiguous``: row -> its candidates (map indices, (C,)) and their
    probabilities (C,); ``landmark`` holds each such row's likeliest candidate."""


def association_probabilities(d2: NDArray[np.float64], S: NDArray[np.float64]
                              ) -> NDArray[np.float64]:
    """
    Return the probabilities of one row's candidate landmarks (module docstring).

    Parameters
    ----------
    d2 : ndarray, shape (C,)
        Squared Mahalanobis distance of the row to each candidate.
    S : ndarray, shape (C, 2, 2)
        Covariance of each difference (row plus landmark) [m^2].

    Returns
    -------
    beta : ndarray, shape (C,)
        ``exp(-d2 / 2) / sqrt(det S)``, normalised to sum 1.

    """
    log_w = -0.5 * np.asarray(d2, dtype=np.float64) - 0.5 * np.log(np.linalg.det(S))
    beta = np.exp(log_w - log_w.max())
    return beta / beta.sum()


class MapAssociation:
    """
    The map's spatial index, kept from one ``set_map`` to the next (a snapshot).

    Parameters
    ----------
    m_map : ndarray, shape (K, 2)
        Landmark positions [m].
    P_map : ndarray, shape (K, 2, 2)
        Their covariances [m^2].
    method : str
        ``nn`` or ``jcbb``.
    probability : float
        Gate probability in (0, 1).
    take_ambiguous : bool
        Keep the method's choice for a row with several candidates (else it is left
        out, counted ambiguous).
    merge_ambiguous : bool
        Apply such a row once per candidate and combine (``localizer.mixture``);
        overrides ``take_ambiguous``.

    Raises
    ------
    ValueError
        If ``method`` is not ``nn`` or ``jcbb`` or a shape is wrong.

    """

    def __init__(self, m_map: NDArray[np.float64], P_map: NDArray[np.float64],
                 method: str, probability: float, take_ambiguous: bool = False,
                 merge_ambiguous: bool = False) -> None:
        """Build the index of the map (class docstring)."""
        self.take_ambiguous = bool(take_ambiguous)
        self.merge_ambiguous = bool(merge_ambiguous)
        self._P = np.asarray(P_map, np.float64)
        if method not in ('nn', 'jcbb'):
            raise ValueError(f"association method must be 'nn' or 'jcbb', got {method!r}")
        self.method = method
        self.probability = float(probability)
        self.index = LandmarkIndex(m_map, P_map, np.zeros(len(m_map), np.int64))

    def assign(self, x: NDArray[np.float64], P: NDArray[np.float64],
               z: NDArray[np.float64], R: NDArray[np.float64]) -> Assigned:
        """
        Pair range-bearing rows seen from pose ``x`` with landmarks of the map.

        Parameters
        ----------
        x : ndarray, shape (3,)
            Pose at the rows' stamp.
        P : ndarray, shape (3, 3)
            Its covariance.
        z : ndarray, shape (N, 2)
            Range [m] and bearing [rad] per row (both finite).
        R : ndarray, shape (N, 2, 2)
            Sensor noise per row.

        Returns
        -------
        Assigned

        """
        n = len(z)
        landmark = np.full(n, -1, np.intp)
        placeable = np.all(np.isfinite(z), axis=1) & (z[:, 0] >= MIN_RANGE)
        if len(self.index) == 0 or not placeable.any():
            return Assigned(landmark, 0, n)
        rows = np.flatnonzero(placeable)
        m_obs, P_obs = landmark_to_world(np.tile(x, (len(rows), 1)),
                                         np.tile(P, (len(rows), 1, 1)), z[rows], R[rows])
        classes = np.zeros(len(rows), np.int64)
        cands = candidates(self.index, m_obs, P_obs, classes, self.probability)
        if self.method == 'nn':
            result = nearest_neighbour(cands)
        else:
            result = jcbb(cands, self.index, m_obs, scan_covariance(m_obs, P_obs, x[:2], P))
        chosen = result.assignment.copy()
        ambiguous, merged = 0, None
        if self.merge_ambiguous:
            merged = {int(rows[r]): v
                      for r, v in self._merge(cands, P_obs, result.ambiguous, chosen).items()}
        elif not self.take_ambiguous:
            chosen[result.ambiguous] = -1
            ambiguous = int(np.count_nonzero(result.assignment[result.ambiguous] >= 0))
        landmark[rows] = chosen
        return Assigned(landmark, ambiguous, int(np.count_nonzero(landmark < 0)) - ambiguous,
                        merged)

    def _merge(self, cands, P_obs, ambiguous, chosen):
        """Return row -> (candidates, probabilities); set ``chosen`` to the likeliest."""
        out = {}
        for row in np.asarray(ambiguous, np.intp).tolist():
            sel = cands.rows == row
            if np.count_nonzero(sel) < 2:
                continue
            j = cands.landmarks[sel]
            beta = association_probabilities(cands.d2[sel], P_obs[row] + self._P[j])
            chosen[row] = j[int(np.argmax(beta))]
            out[row] = (j, beta)
        return out


def label_rows(association: MapAssociation, estimate, map_ids: NDArray[np.int64],
               ids: NDArray[np.int64], z: NDArray[np.float64], kind: NDArray[np.int64],
               R: NDArray[np.float64]):
    """
    Return ``ids`` with the rows without ID given the ID of their landmark, and counts.

    Parameters
    ----------
    association : MapAssociation
        The map's index.
    estimate : localizer.Estimate or None
        Pose and covariance at the rows' stamp (``x`` (3,), ``P`` (3, 3)); None: none
        is associated.
    map_ids : ndarray of int, shape (K,)
        Landmark ID of each map index.
    ids : ndarray of int, shape (N,)
        Row IDs, ``UNKNOWN_ID`` for none.
    z, R, kind : ndarray, shapes (N, 2), (N, 2, 2), (N,)
        The rows, their noise and kinds (``update.RANGE_BEARING`` ...).

    Returns
    -------
    ids : ndarray of int, shape (N,)
        A copy with the associated rows labelled.
    counts : dict
        ``associated``, ``association_ambiguous`` (several candidates left unsettled:
        skipped), ``association_unmatched`` (no compatible landmark: skipped),
        ``association_partial`` (partial rows: not associated) and
        ``association_merged`` (rows applied once per candidate).
    merged : dict
        Row index (into ``ids``) -> (candidate IDs (C,), probabilities (C,)) of the rows
        to apply once per candidate (``merge_ambiguous``; their ``ids`` the likeliest
        candidate's, which names them for the correlated noise).

    """
    unknown = ids == UNKNOWN_ID
    rows = np.flatnonzero(unknown & (kind == RANGE_BEARING))
    counts = {'associated': 0, 'association_ambiguous': 0,
              'association_unmatched': len(rows),
              'association_partial': int(np.count_nonzero(unknown)) - len(rows),
              'association_merged': 0}
    if estimate is None or not len(rows):
        return ids, counts, {}
    found = association.assign(estimate.x, estimate.P, z[rows], R[rows])
    ids = ids.copy()
    hit = found.landmark >= 0
    ids[rows[hit]] = map_ids[found.landmark[hit]]
    merged = {}
    if found.merged is not None:
        merged = {int(rows[r]): (map_ids[j], beta) for r, (j, beta) in found.merged.items()}
    counts.update(associated=int(hit.sum()), association_ambiguous=found.ambiguous,
                  association_unmatched=found.unmatched, association_merged=len(merged))
    return ids, counts, merged
