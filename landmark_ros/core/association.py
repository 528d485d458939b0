"""
Data association of unlabelled observations with landmarks of a map.

One robot message brings ``N`` world-frame observation rows without landmark IDs;
each is to be paired with one of the ``K`` landmarks of the map, or with none (a new
landmark or clutter). The rows of one message share the robot's pose error, so
their errors are correlated: ``scan_covariance`` builds their joint covariance.

Pipeline: ``LandmarkIndex`` (once per map) -> ``candidates`` (individually
compatible pairs) -> ``nearest_neighbour``, ``global_nearest_neighbour`` or
``joint_compatibility.jcbb`` -> ``Association``.

Symbols
-------
m_map : landmark means in the world, shape (K, 2) [m].
P_map : their covariances, shape (K, 2, 2) [m^2], independent of each other and of
    the scan.
z : observation rows in the world, shape (N, 2) [m].
R : the marginal (total) covariance of each row, shape (N, 2, 2) [m^2]: sensor
    noise, pose and bias terms together, as the observer publishes it.
C_z : joint covariance of the stacked rows ``(x_0, y_0, x_1, y_1, ...)``, shape
    (2N, 2N) [m^2]; its diagonal 2x2 blocks are ``R``.
nu : innovation ``z_i - m_j`` of a pairing, shape (2,) [m].
S : innovation covariance ``R_i + P_map[j]`` (one pairing) or the joint one
    ``C_z[H, H] + blockdiag(P_map[H])`` of a hypothesis ``H`` (2k, 2k).
d2 : squared Mahalanobis distance ``nu^T S^-1 nu`` (2 or 2k degrees of freedom).

Sources
-------
- Nearest neighbour and global nearest neighbour with a gate: Y. Bar-Shalom and
  T. E. Fortmann, *Tracking and Data Association*, Academic Press, 1988; the
  assignment solved by the Jonker-Volgenant method that
  ``scipy.optimize.linear_sum_assignment`` implements (D. F. Crouse, IEEE T-AES
  52(4), 2016).
- Joint compatibility branch and bound: J. Neira and J. D. Tardos, "Data
  association in stochastic mapping using the joint compatibility test", IEEE
  Transactions on Robotics and Automation 17(6), 890-897, 2001.
- The search radius of the spatial index: ``d2 >= |nu|^2 / lambda_max(S)`` and
  ``lambda_max(P + R) <= lambda_max(P) + lambda_max(R)`` (Weyl's inequality).

"""

from dataclasses import dataclass
import functools
import itertools
import math
from typing import List, Optional, Tuple

from landmark_ros.core.arrays import as_matrices, as_vectors
from landmark_ros.core.gating import chi2_threshold, mahalanobis_sq
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.special import chdtri

DEFAULT_PROBABILITY = 0.999
"""Gate probability: a consistent pairing passes its chi-square gate with this probability."""

DEFAULT_MAX_NODES = 5000
"""Nodes (rows evaluated) ``jcbb`` explores before it falls back to the GNN solution."""


@functools.lru_cache(maxsize=16)
def _gate(probability):
    return chi2_threshold(2, probability)


def _largest_eigenvalue(P):
    # Closed form for symmetric 2x2 matrices.
    a, b, c = P[..., 0, 0], 0.5 * (P[..., 0, 1] + P[..., 1, 0]), P[..., 1, 1]
    return 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)


def joint_thresholds(n: int, probability: float = DEFAULT_PROBABILITY) -> NDArray[np.float64]:
    """
    Return the chi-square gates of hypotheses with 0 to ``n`` pairings.

    Parameters
    ----------
    n : int, >= 0
        Largest number of pairings.
    probability : float
        Gate probability in (0, 1).

    Returns
    -------
    ndarray, shape (n + 1,)
        Entry ``k`` is the quantile of the chi-square distribution with ``2 k``
        degrees of freedom at ``probability`` (0 for ``k = 0``).

    Raises
    ------
    ValueError
        If ``probability`` is outside (0, 1).

    """
    if not 0.0 < probability < 1.0:
        raise ValueError(f'probability must lie in (0, 1), got {probability!r}')
    return _joint_thresholds(int(n), float(probability)).copy()


@functools.lru_cache(maxsize=64)
def _joint_thresholds(n, probability):
    thresholds = np.zeros(n + 1)
    thresholds[1:] = chdtri(2.0 * np.arange(1, n + 1), 1.0 - probability)
    thresholds.flags.writeable = False
    return thresholds


def scan_covariance(z: ArrayLike, R: ArrayLike, robot_xy: ArrayLike, P_pose: ArrayLike,
                    R_bias: Optional[ArrayLike] = None,
                    sensor_xy: Optional[ArrayLike] = None,
                    range_scale_variance: float = 0.0) -> NDArray[np.float64]:
    """
    Return the joint covariance of the rows of one message, shared pose error included.

    A row is ``m = t + Rot(theta) p`` for the robot pose ``(t, theta)`` and a point
    ``p`` fixed in the robot frame, so ``J_m_pose = [[1, 0, -(m_y - y)], [0, 1, m_x - x]]``
    with ``(x, y)`` the robot position: every row moves with the same pose error.
    With a sensor bias ``beta`` shared by the message (a range and bearing offset of
    covariance ``R_bias``), ``J_m_beta = [[e_x / r, -e_y], [e_y / r, e_x]]`` with
    ``e = m - sensor_xy`` and ``r = |e|``. A range scale error ``s`` shared by the
    message (variance ``range_scale_variance``) moves a row by ``s e``, so
    ``J_m_s = e``. Block ``(i, j != i)`` is

        ``J_i_pose P_pose J_j_pose^T + J_i_beta R_bias J_j_beta^T
        + range_scale_variance e_i e_j^T``

    and block ``(i, i)`` is ``R[i]``, which must already hold these terms (it does
    when the observer computes it with ``landmarks.landmark_to_world_dependent``:
    pose, bias and noise). First order, evaluated at the published rows. Per message
    the fuser needs the robot position ``robot_xy`` and ``P_pose`` (and ``R_bias``
    with ``sensor_xy`` if the bias is modelled); rows of different messages are
    taken as independent.

    Parameters
    ----------
    z : array_like, shape (N, 2) [m]
        Observation rows in the world.
    R : array_like, shape (N, 2, 2) [m^2]
        Total covariance of each row.
    robot_xy : array_like, shape (2,) [m]
        Robot position the message was observed from (the pose's ``x, y``, not the
        sensor's).
    P_pose : array_like, shape (3, 3)
        Covariance of the robot pose ``(x [m], y [m], theta [rad])``. Zeros give
        independent rows (a block-diagonal result).
    R_bias : array_like, shape (2, 2), optional
        Covariance of a sensor bias shared by the message, in (range [m^2],
        bearing [rad^2]); ``None`` for none.
    sensor_xy : array_like, shape (2,) [m], optional
        Sensor position in the world, for the bias term; default ``robot_xy``.
    range_scale_variance : float
        Variance of a relative range error shared by the message (with ``R_bias``;
        ``R[i]`` must contain its term too); 0 for none.

    Returns
    -------
    C_z : ndarray, shape (2N, 2N) [m^2]
        Symmetric, positive semi-definite; rows ordered ``(x_0, y_0, x_1, ...)``.

    Raises
    ------
    ValueError
        If a shape is wrong, or if some ``R[i]`` is smaller than the shared terms
        it must contain (the result would not be a covariance).

    """
    z = as_vectors(z, 2, 'z').reshape(-1, 2)
    n = len(z)
    R = as_matrices(R, 2, 'R')
    if R.shape != (n, 2, 2):
        raise ValueError(f'R must have shape ({n}, 2, 2), got {R.shape}')
    robot_xy = as_vectors(robot_xy, 2, 'robot_xy')
    P_pose = as_matrices(P_pose, 3, 'P_pose')
    if robot_xy.shape != (2,) or P_pose.shape != (3, 3):
        raise ValueError('robot_xy and P_pose are one per message: shapes (2,) and (3, 3)')
    e = z - robot_xy
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2] = -e[:, 1]
    J[:, 1, 2] = e[:, 0]
    G = J.reshape(2 * n, 3)
    C_z = G @ P_pose @ G.T
    if R_bias is not None:
        R_bias = as_matrices(R_bias, 2, 'R_bias')
        sensor_xy = robot_xy if sensor_xy is None else as_vectors(sensor_xy, 2, 'sensor_xy')
        e = z - sensor_xy
        r = np.hypot(e[:, 0], e[:, 1])
        if np.any(r <= 0.0):
            raise ValueError('a row coincides with the sensor: the bias term is undefined')
        B = np.stack([np.stack([e[:, 0] / r, -e[:, 1]], -1),
                      np.stack([e[:, 1] / r, e[:, 0]], -1)], axis=1).reshape(2 * n, 2)
        C_z += B @ R_bias @ B.T
        if range_scale_variance:
            flat = e.reshape(2 * n)
            C_z += range_scale_variance * np.outer(flat, flat)
    C_z = 0.5 * (C_z + C_z.T)
    blocks = C_z.reshape(n, 2, n, 2)
    diagonal = np.arange(n)
    independent = R - blocks[diagonal, :, diagonal, :]
    a, b, c = independent[:, 0, 0], independent[:, 0, 1], independent[:, 1, 1]
    smallest = 0.5 * (a + c) - np.hypot(0.5 * (a - c), 0.5 * (b + independent[:, 1, 0]))
    tolerance = 1e-9 * np.maximum(1.0, np.abs(R).max(axis=(1, 2)))
    if np.any(smallest < -tolerance):
        rows = np.flatnonzero(smallest < -tolerance)
        raise ValueError(f'rows {rows.tolist()}: R is smaller than the pose and bias terms '
                         'it must contain')
    blocks[diagonal, :, diagonal, :] = R
    return C_z


class LandmarkIndex:
    """
    Spatial index over the landmark means of a map (a snapshot).

    Landmarks are grouped in tiers of similar largest covariance eigenvalue (within
    a factor ``tier_ratio``), one ``scipy.spatial.cKDTree`` per tier, so that one
    badly known landmark does not widen the search radius for all the others.
    Rebuild it (or build a new one) when the map changes: ``candidates`` evaluates
    the arrays held here.

    Parameters
    ----------
    m_map : array_like, shape (K, 2) [m]
        Landmark means.
    P_map : array_like, shape (K, 2, 2) [m^2]
        Landmark covariances.
    classes : array_like of int, shape (K,)
        Landmark classes; a row is compared only with landmarks of its class.
    tier_ratio : float, > 1
        Largest ratio of largest eigenvalues within one tier.

    Raises
    ------
    ValueError
        If the shapes disagree or ``tier_ratio <= 1``.

    """

    def __init__(self, m_map: ArrayLike, P_map: ArrayLike, classes: ArrayLike,
                 tier_ratio: float = 4.0) -> None:
        self.m_map = as_vectors(m_map, 2, 'm_map').reshape(-1, 2)
        count = len(self.m_map)
        self.P_map = as_matrices(P_map, 2, 'P_map').reshape(-1, 2, 2)
        self.classes = np.asarray(classes).reshape(-1)
        if len(self.P_map) != count or len(self.classes) != count:
            raise ValueError(f'm_map, P_map and classes disagree on K: {count}, '
                             f'{len(self.P_map)}, {len(self.classes)}')
        if not tier_ratio > 1.0:
            raise ValueError(f'tier_ratio must exceed 1, got {tier_ratio!r}')
        largest = _largest_eigenvalue(self.P_map)
        self.tiers: List[Tuple[cKDTree, NDArray[np.intp], float]] = []
        """List of ``(tree, landmark ids, largest eigenvalue in the tier [m^2])``."""
        if count == 0:
            return
        floor = max(float(largest.min()), 1e-300)
        tier = np.floor(np.log(np.maximum(largest, floor) / floor) / math.log(tier_ratio))
        for value in np.unique(tier):
            ids = np.flatnonzero(tier == value)
            self.tiers.append((cKDTree(self.m_map[ids]), ids, float(largest[ids].max())))

    def __len__(self) -> int:
        """Return the number of landmarks ``K``."""
        return len(self.m_map)


@dataclass(frozen=True)
class Candidates:
    """
    Individually compatible pairings of a scan's rows with landmarks, sorted by row, then d2.

    Attributes
    ----------
    rows : ndarray of int, shape (M,)
        Row of each pairing.
    landmarks : ndarray of int, shape (M,)
        Landmark (index into the map) of each pairing.
    d2 : ndarray, shape (M,)
        Squared Mahalanobis distance of each pairing, with ``S = R[row] + P_map[landmark]``.
    n_rows : int
        Rows ``N`` of the scan.
    threshold : float
        The gate the pairings passed: chi-square, 2 degrees of freedom.
    probability : float
        The gate probability it was derived from.

    """

    rows: NDArray[np.intp]
    landmarks: NDArray[np.intp]
    d2: NDArray[np.float64]
    n_rows: int
    threshold: float
    probability: float

    def counts(self) -> NDArray[np.intp]:
        """Return the number of candidates of each row, shape (N,)."""
        return np.bincount(self.rows, minlength=self.n_rows)


@dataclass(frozen=True)
class Association:
    """
    The result of one association method on one scan.

    Attributes
    ----------
    assignment : ndarray of int, shape (N,)
        Landmark of each row, -1 for none (new landmark or clutter).
    d2 : ndarray, shape (N,)
        Individual squared Mahalanobis distance of each assigned row, NaN for none.
    ambiguous : ndarray of int, shape (A,)
        Rows with more than one candidate whose choice no joint test settled.
    method : str
        ``'nn'``, ``'gnn'`` or ``'jcbb'``.
    fallback : bool
        True when ``jcbb`` hit its node bound and returned the GNN solution.
    joint_d2 : float
        ``jcbb``: joint squared Mahalanobis distance of the assigned rows (2k
        degrees of freedom); NaN for the other methods and after a fallback.
    nodes : int
        ``jcbb``: rows evaluated during the search; 0 for the other methods.

    """

    assignment: NDArray[np.intp]
    d2: NDArray[np.float64]
    ambiguous: NDArray[np.intp]
    method: str
    fallback: bool = False
    joint_d2: float = float('nan')
    nodes: int = 0

    @property
    def n_assigned(self) -> int:
        """Return the number of assigned rows."""
        return int(np.count_nonzero(self.assignment >= 0))


def _check_scan(z, R, classes):
    z = as_vectors(z, 2, 'z').reshape(-1, 2)
    R = as_matrices(R, 2, 'R').reshape(-1, 2, 2)
    classes = np.asarray(classes).reshape(-1)
    if len(R) != len(z) or len(classes) != len(z):
        raise ValueError(f'z, R and classes disagree on N: {len(z)}, {len(R)}, {len(classes)}')
    return z, R, classes


def candidates(index: LandmarkIndex, z: ArrayLike, R: ArrayLike, classes: ArrayLike,
               probability: float = DEFAULT_PROBABILITY) -> Candidates:
    """
    Return the individually compatible pairings of a scan's rows with the map.

    Each row is searched in the index within the radius
    ``sqrt(threshold (lambda_max(P_tier) + lambda_max(R[i])))``, which contains
    every landmark that can pass the gate; then landmarks of another class are
    dropped and the rest gated on ``d2 <= chi2_threshold(2, probability)`` with
    ``S = P_map + R`` (individual compatibility; the rows' cross-covariance plays no
    part here).

    Parameters
    ----------
    index : LandmarkIndex
        The map.
    z : array_like, shape (N, 2) [m]
        Observation rows in the world.
    R : array_like, shape (N, 2, 2) [m^2]
        Total covariance of each row.
    classes : array_like of int, shape (N,)
        Class of each row.
    probability : float
        Gate probability in (0, 1).

    Returns
    -------
    Candidates

    Raises
    ------
    ValueError
        If the shapes disagree or ``probability`` is outside (0, 1).

    """
    z, R, classes = _check_scan(z, R, classes)
    threshold = _gate(probability)
    rows_parts, landmark_parts = [], []
    if len(z):
        spread = _largest_eigenvalue(R)
        for tree, ids, largest in index.tiers:
            # A hair wider than the bound, so rounding cannot drop a pair on the gate.
            radius = np.sqrt(threshold * (largest + spread)) * (1.0 + 1e-9)
            found = tree.query_ball_point(z, radius, return_sorted=False)
            counts = np.fromiter(map(len, found), dtype=np.intp, count=len(found))
            total = int(counts.sum())
            if total == 0:
                continue
            rows_parts.append(np.repeat(np.arange(len(z)), counts))
            flat = np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp, count=total)
            landmark_parts.append(ids[flat])
    if rows_parts:
        rows = np.concatenate(rows_parts)
        landmarks = np.concatenate(landmark_parts)
        same = index.classes[landmarks] == classes[rows]
        rows, landmarks = rows[same], landmarks[same]
        d2 = np.atleast_1d(mahalanobis_sq(z[rows], index.m_map[landmarks],
                                          R[rows] + index.P_map[landmarks]))
        keep = d2 <= threshold
        rows, landmarks, d2 = rows[keep], landmarks[keep], d2[keep]
        order = np.lexsort((d2, rows))
        rows, landmarks, d2 = rows[order], landmarks[order], d2[order]
    else:
        rows = landmarks = np.zeros(0, dtype=np.intp)
        d2 = np.zeros(0)
    return Candidates(rows=rows, landmarks=landmarks, d2=d2, n_rows=len(z),
                      threshold=threshold, probability=probability)


def ambiguous_rows(cands: Candidates) -> NDArray[np.intp]:
    """
    Return the rows with more than one candidate (no joint test to choose between them).

    Parameters
    ----------
    cands : Candidates
        From ``candidates``.

    Returns
    -------
    ndarray of int, shape (A,)
        Row indices, ascending.

    """
    return np.flatnonzero(cands.counts() > 1)


def _result(cands, rows, landmarks, d2, method, **kwargs):
    assignment = np.full(cands.n_rows, -1, dtype=np.intp)
    row_d2 = np.full(cands.n_rows, np.nan)
    assignment[rows] = landmarks
    row_d2[rows] = d2
    ambiguous = kwargs.pop('ambiguous', None)
    if ambiguous is None:
        ambiguous = ambiguous_rows(cands)
    return Association(assignment=assignment, d2=row_d2, ambiguous=ambiguous, method=method,
                       **kwargs)


def nearest_neighbour(cands: Candidates) -> Association:
    """
    Pair each row independently with its candidate of smallest d2 (NN).

    Two rows may take the same landmark. Source: Bar-Shalom and Fortmann (1988).

    Parameters
    ----------
    cands : Candidates
        From ``candidates``.

    Returns
    -------
    Association
        ``method='nn'``; every row with more than one candidate is ambiguous.

    """
    # Candidates are sorted by row, then d2: the first of each row is its nearest.
    rows, first = np.unique(cands.rows, return_index=True)
    return _result(cands, rows, cands.landmarks[first], cands.d2[first], 'nn')


def _gnn_pairs(cands):
    """Return the rows, landmarks and d2 of the minimum-cost one-to-one assignment."""
    if len(cands.rows) == 0:
        return cands.rows, cands.landmarks, cands.d2
    rows, row_of = np.unique(cands.rows, return_inverse=True)
    landmarks, landmark_of = np.unique(cands.landmarks, return_inverse=True)
    n, k = len(rows), len(landmarks)
    # Columns: the landmarks, then one "unassigned" column per row costing the gate.
    cost = np.full((n, k + n), np.inf)
    cost[row_of, landmark_of] = cands.d2
    cost[np.arange(n), k + np.arange(n)] = cands.threshold
    from scipy.optimize import linear_sum_assignment  # a second or more: when first needed
    assigned_row, column = linear_sum_assignment(cost)
    real = column < k
    assigned_row, column = assigned_row[real], column[real]
    return rows[assigned_row], landmarks[column], cost[assigned_row, column]


def global_nearest_neighbour(cands: Candidates) -> Association:
    """
    Pair rows with landmarks one-to-one at the smallest total d2 (GNN).

    Minimises the sum of d2 over the gated pairs, where leaving a row unassigned
    costs the gate ``cands.threshold``; solved with
    ``scipy.optimize.linear_sum_assignment`` on the rows and landmarks that have
    candidates. Sources: Bar-Shalom and Fortmann (1988); Crouse (2016).

    Parameters
    ----------
    cands : Candidates
        From ``candidates``.

    Returns
    -------
    Association
        ``method='gnn'``; every row with more than one candidate is ambiguous.

    """
    rows, landmarks, d2 = _gnn_pairs(cands)
    return _result(cands, rows, landmarks, d2, 'gnn')
