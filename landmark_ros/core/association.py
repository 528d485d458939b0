"""
Data association of unlabelled observations with landmarks of a map.

One robot message brings ``N`` world-frame observation rows without landmark IDs;
each is to be paired with one of the ``K`` landmarks of the map, or with none (a new
landmark or clutter). The rows of one message share the robot's pose error, so
their errors are correlated: ``scan_covariance`` builds their joint covariance.

Pipeline: ``LandmarkIndex`` (once per map) -> ``candidates`` (individually
compatible pairs) -> ``nearest_neighbour``, ``global_nearest_neighbour`` or
``jcbb`` -> ``Association``.

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

from landmark_ros.core._arrays import as_matrices, as_vectors
from landmark_ros.core.gating import chi2_threshold, mahalanobis_sq
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import cho_factor, cho_solve, cholesky, solve_triangular
from scipy.optimize import linear_sum_assignment
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
                    sensor_xy: Optional[ArrayLike] = None) -> NDArray[np.float64]:
    """
    Return the joint covariance of the rows of one message, shared pose error included.

    A row is ``m = t + Rot(theta) p`` for the robot pose ``(t, theta)`` and a point
    ``p`` fixed in the robot frame, so ``J_m_pose = [[1, 0, -(m_y - y)], [0, 1, m_x - x]]``
    with ``(x, y)`` the robot position: every row moves with the same pose error.
    With a sensor bias ``beta`` shared by the message (a range and bearing offset of
    covariance ``R_bias``), ``J_m_beta = [[e_x / r, -e_y], [e_y / r, e_x]]`` with
    ``e = m - sensor_xy`` and ``r = |e|``. Block ``(i, j != i)`` is

        ``J_i_pose P_pose J_j_pose^T + J_i_beta R_bias J_j_beta^T``

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


class _Exhausted(Exception):
    """The search reached its node bound."""


class _Search:
    """
    Depth-first joint compatibility branch and bound over the rows with candidates.

    The Cholesky factor ``L`` of the joint innovation covariance of the current
    hypothesis grows by one 2x2 block row per pairing (or by several at once along
    a run of rows with a single candidate), and ``w = L^-1 nu`` with it, so the
    joint d2 of a new pairing costs one triangular solve: ``d2 + |w_new|^2``.
    """

    def __init__(self, order, cand_landmarks, cand_nu, cand_S, single, C_z, thresholds,
                 max_nodes):
        self.order = order
        self.cand_landmarks = cand_landmarks
        self.cand_nu = cand_nu
        self.cand_S = cand_S
        self.C_z = C_z
        self.thresholds = thresholds
        self.max_nodes = max_nodes
        n = len(order)
        self.n = n
        # Rows with a single candidate come first; the search descends them in bulk.
        self.single_landmarks, self.single_nu, self.single_S = single
        self.n_single = len(self.single_landmarks)
        self.L = np.zeros((2 * n, 2 * n))
        self.w = np.zeros(2 * n)
        self.coords = np.zeros(2 * n, dtype=np.intp)
        self.used = set()
        self.current = np.full(n, -1, dtype=np.intp)
        self.best = self.current.copy()
        self.best_n = 0
        self.best_d2 = 0.0
        self.nodes = 0

    def _count(self, nodes):
        self.nodes += nodes
        if self.nodes > self.max_nodes:
            raise _Exhausted()

    def _leaf(self, k, d2):
        if k > self.best_n or (k == self.best_n and d2 < self.best_d2):
            self.best_n, self.best_d2 = k, d2
            self.best = self.current.copy()

    def _star(self, p, k, d2):
        # Leave row p unpaired; worth it only if all later rows could still win.
        if k + self.n - p - 1 > self.best_n:
            self.node(p + 1, k, d2)

    def node(self, p, k, d2):
        """Explore position ``p`` with ``k`` pairings of joint distance ``d2`` so far."""
        if p == self.n:
            self._leaf(k, d2)
            return
        if p < self.n_single - 1 and self._run(p, k, d2):
            return
        self._count(1)
        row = self.order[p]
        landmarks, nu, S = self.cand_landmarks[p], self.cand_nu[p], self.cand_S[p]
        if k:
            b = solve_triangular(self.L[:2 * k, :2 * k],
                                 self.C_z[2 * row:2 * row + 2, self.coords[:2 * k]].T,
                                 lower=True, check_finite=False)
            S = S - b.T @ b
            nu = nu - b.T @ self.w[:2 * k]
        with np.errstate(invalid='ignore', divide='ignore'):
            l00 = np.sqrt(S[:, 0, 0])
            l10 = S[:, 1, 0] / l00
            l11 = np.sqrt(S[:, 1, 1] - l10 * l10)
            u0 = nu[:, 0] / l00
            u1 = (nu[:, 1] - l10 * u0) / l11
        d2_new = d2 + u0 * u0 + u1 * u1
        later = self.n - p - 1
        for c in np.argsort(d2_new):
            if not d2_new[c] <= self.thresholds[k + 1]:
                break
            landmark = landmarks[c]
            if landmark in self.used:
                continue
            if not (k + 1 + later > self.best_n
                    or (k + 1 + later == self.best_n and d2_new[c] < self.best_d2)):
                continue
            i = 2 * k
            if k:
                self.L[i:i + 2, :i] = b.T
            self.L[i, i], self.L[i, i + 1], self.L[i + 1, i], self.L[i + 1, i + 1] = (
                l00[c], 0.0, l10[c], l11[c])
            self.w[i], self.w[i + 1] = u0[c], u1[c]
            self.coords[i], self.coords[i + 1] = 2 * row, 2 * row + 1
            self.used.add(landmark)
            self.current[p] = landmark
            self.node(p + 1, k + 1, d2_new[c])
            self.used.discard(landmark)
            self.current[p] = -1
        self._star(p, k, d2)

    def _run(self, p, k, d2):
        """
        Descend the rows ``p`` to ``n_single - 1`` (one candidate each) in one block.

        Equivalent to visiting them one at a time: the factor of the first ``t``
        pairings is the leading block of the factor of all, so the unpaired (star)
        branches are taken afterwards, deepest first, from the truncated state.
        Returns False (nothing done) if the block factorisation fails.
        """
        stop = self.n_single
        landmarks = self.single_landmarks[p:stop]
        # Pairings stop at the first landmark already used, here or above.
        limit = len(landmarks)
        seen = set(self.used)
        for t, landmark in enumerate(landmarks):
            if landmark in seen:
                limit = t
                break
            seen.add(landmark)
        if limit == 0:
            return False
        rows = self.order[p:p + limit]
        coords = np.stack([2 * rows, 2 * rows + 1], axis=-1).reshape(-1)
        S = self.C_z[np.ix_(coords, coords)]
        blocks = S.reshape(limit, 2, limit, 2)
        diagonal = np.arange(limit)
        blocks[diagonal, :, diagonal, :] = self.single_S[p:p + limit]
        nu = self.single_nu[p:p + limit].reshape(-1)
        i = 2 * k
        if k:
            X = solve_triangular(self.L[:i, :i], self.C_z[np.ix_(self.coords[:i], coords)],
                                 lower=True, check_finite=False)
            S -= X.T @ X
            nu -= X.T @ self.w[:i]
        try:
            L_new = cholesky(S, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return False
        w_new = solve_triangular(L_new, nu, lower=True, check_finite=False)
        d2_prefix = d2 + np.concatenate([[0.0], np.cumsum((w_new * w_new).reshape(-1, 2).sum(1))])
        passed = d2_prefix[1:] <= self.thresholds[k + 1:k + 1 + limit]
        paired = limit if passed.all() else int(np.argmin(passed))
        self._count(paired + 1)
        j = 2 * paired
        if k:
            self.L[i:i + j, :i] = X.T[:j]
        self.L[i:i + j, i:i + j] = L_new[:j, :j]
        self.w[i:i + j] = w_new[:j]
        self.coords[i:i + j] = coords[:j]
        self.used.update(landmarks[:paired].tolist())
        self.current[p:p + paired] = landmarks[:paired]
        if p + paired == stop:
            self.node(stop, k + paired, d2_prefix[paired])
        else:
            # Row p + paired cannot be paired (joint gate or landmark taken).
            self._star(p + paired, k + paired, d2_prefix[paired])
        for t in range(paired - 1, -1, -1):
            self.used.discard(landmarks[t])
            self.current[p + t] = -1
            self._star(p + t, k + t, d2_prefix[t])
        return True


def jcbb(cands: Candidates, index: LandmarkIndex, z: ArrayLike, C_z: ArrayLike,
         max_nodes: int = DEFAULT_MAX_NODES) -> Association:
    """
    Pair rows with landmarks by joint compatibility branch and bound (JCBB).

    Finds the one-to-one hypothesis with the most pairings whose joint innovation
    passes the chi-square gate with ``2 k`` degrees of freedom at every depth of the
    search: the innovations of the ``k`` pairings stacked, with covariance
    ``C_z[H, H] + blockdiag(P_map[H])`` (the scan's cross-covariance through the
    shared pose error plus the landmark blocks). Among hypotheses found with the
    same number of pairings the smaller joint d2 wins. Only individually compatible
    pairs (``cands``) are tried; rows without candidates stay unassigned. Rows are
    visited by increasing number of candidates; the joint d2 of a new pairing comes
    from the Cholesky factor of the current hypothesis grown by one block (one
    triangular solve), and runs of single-candidate rows are factorised in one block.
    Unpaired branches are bounded as in the paper: explored only when they could
    reach strictly more pairings than the best so far. Beyond ``max_nodes`` rows
    evaluated, the search stops and the GNN solution is returned with
    ``fallback=True``. Source: Neira and Tardos, IEEE T-RA 17(6), 2001.

    A paired row is reported ambiguous when, given all the other pairings, another
    of its candidates would also pass the joint gate (the joint test did not break
    the tie); after a fallback every row with several candidates is.

    Parameters
    ----------
    cands : Candidates
        From ``candidates`` with the same ``index``, ``z`` and the rows' ``R``.
    index : LandmarkIndex
        The map.
    z : array_like, shape (N, 2) [m]
        Observation rows in the world.
    C_z : array_like, shape (2N, 2N) [m^2]
        Joint covariance of the rows, from ``scan_covariance`` (its diagonal blocks
        the ``R`` of ``cands``); ``scan_covariance(z, R, xy, zeros((3, 3)))`` for
        independent rows.
    max_nodes : int
        Search bound, in rows evaluated.

    Returns
    -------
    Association
        ``method='jcbb'``, with ``joint_d2``, ``nodes`` and ``fallback``.

    Raises
    ------
    ValueError
        If the shapes disagree.

    """
    z = as_vectors(z, 2, 'z').reshape(-1, 2)
    C_z = np.asarray(C_z, dtype=np.float64)
    n_rows = cands.n_rows
    if len(z) != n_rows or C_z.shape != (2 * n_rows, 2 * n_rows):
        raise ValueError(f'z and C_z must have shapes ({n_rows}, 2) and '
                         f'({2 * n_rows}, {2 * n_rows}), got {z.shape} and {C_z.shape}')
    rows, starts, counts = np.unique(cands.rows, return_index=True, return_counts=True)
    if len(rows) == 0:
        return _result(cands, rows, rows, np.zeros(0), 'jcbb', joint_d2=0.0)
    order = np.lexsort((cands.d2[starts], counts))
    # Innovations and their individual covariances, all pairs at once, then per row.
    R_pairs = C_z.reshape(n_rows, 2, n_rows, 2)[cands.rows, :, cands.rows, :]
    nu = z[cands.rows] - index.m_map[cands.landmarks]
    S = R_pairs + index.P_map[cands.landmarks]
    landmarks = cands.landmarks.tolist()
    parts = [slice(starts[q], starts[q] + counts[q]) for q in order.tolist()]
    cand_landmarks = [landmarks[part] for part in parts]
    cand_nu = [nu[part] for part in parts]
    cand_S = [S[part] for part in parts]
    thresholds = _joint_thresholds(len(rows), float(cands.probability))
    first = starts[order[:np.count_nonzero(counts == 1)]]
    single = (cands.landmarks[first], nu[first], S[first])
    search = _Search(rows[order], cand_landmarks, cand_nu, cand_S, single, C_z, thresholds,
                     max_nodes)
    try:
        search.node(0, 0, 0.0)
    except _Exhausted:
        gnn_rows, gnn_landmarks, gnn_d2 = _gnn_pairs(cands)
        return _result(cands, gnn_rows, gnn_landmarks, gnn_d2, 'jcbb', fallback=True,
                       nodes=search.nodes)
    paired = search.best >= 0
    best_rows, best_landmarks = rows[order][paired], search.best[paired]
    pair_d2 = _pair_d2(cands, best_rows, best_landmarks)
    ambiguous = _jointly_ambiguous(cands, index, z, C_z, best_rows, best_landmarks,
                                   thresholds[len(best_rows)])
    return _result(cands, best_rows, best_landmarks, pair_d2, 'jcbb',
                   ambiguous=ambiguous, joint_d2=float(search.best_d2), nodes=search.nodes)


def _pair_d2(cands, rows, landmarks):
    """Return the individual d2 of given (row, landmark) pairs, all among the candidates."""
    stride = int(max(cands.landmarks.max(initial=0), landmarks.max(initial=0))) + 1
    keys = cands.rows.astype(np.int64) * stride + cands.landmarks
    order = np.argsort(keys)
    found = order[np.searchsorted(keys, rows.astype(np.int64) * stride + landmarks,
                                  sorter=order)]
    return cands.d2[found]


def joint_mahalanobis_sq(index: LandmarkIndex, z: ArrayLike, C_z: ArrayLike, rows: ArrayLike,
                         landmarks: ArrayLike) -> float:
    """
    Return the joint squared Mahalanobis distance of a hypothesis.

    Parameters
    ----------
    index : LandmarkIndex
        The map.
    z : array_like, shape (N, 2) [m]
        Observation rows in the world.
    C_z : array_like, shape (2N, 2N) [m^2]
        Joint covariance of the rows.
    rows : array_like of int, shape (k,)
        Paired rows.
    landmarks : array_like of int, shape (k,)
        Their landmarks, distinct.

    Returns
    -------
    float
        ``nu^T S^-1 nu`` with ``nu`` the stacked innovations and
        ``S = C_z[H, H] + blockdiag(P_map[landmarks])``; chi-square with ``2 k``
        degrees of freedom for a correct hypothesis. 0 for ``k = 0``.

    """
    rows = np.asarray(rows, dtype=np.intp)
    landmarks = np.asarray(landmarks, dtype=np.intp)
    if len(rows) == 0:
        return 0.0
    nu, S = _joint_innovation(index, np.asarray(z, dtype=np.float64), C_z, rows, landmarks)
    return float(nu @ cho_solve(cho_factor(S, lower=True), nu))


def _joint_innovation(index, z, C_z, rows, landmarks):
    coords = np.stack([2 * rows, 2 * rows + 1], axis=-1).reshape(-1)
    S = np.array(np.asarray(C_z)[np.ix_(coords, coords)])
    blocks = S.reshape(len(rows), 2, len(rows), 2)
    diagonal = np.arange(len(rows))
    blocks[diagonal, :, diagonal, :] += index.P_map[landmarks]
    return (z[rows] - index.m_map[landmarks]).reshape(-1), S


def _jointly_ambiguous(cands, index, z, C_z, rows, landmarks, threshold):
    """
    Return the paired rows for which another candidate also passes, given the rest.

    With ``Lambda = S^-1`` of the hypothesis and ``y = Lambda nu``, the innovation of
    paired row ``t`` given all the others has mean ``nu_t - Sigma_t y_t`` and
    covariance ``Sigma_t = Lambda_tt^-1``, and the others alone have joint d2
    ``d2 - y_t^T Sigma_t y_t``. Swapping landmark ``j`` for ``j'`` changes only the
    innovation and the ``P_map`` block: the swapped hypothesis's joint d2 follows
    in closed form, for every row and alternative at once.
    """
    if len(rows) == 0:
        return np.zeros(0, dtype=np.intp)
    position = np.full(cands.n_rows, -1, dtype=np.intp)
    position[rows] = np.arange(len(rows))
    alternative = (position[cands.rows] >= 0) & (
        cands.landmarks != np.where(position[cands.rows] >= 0,
                                    landmarks[position[cands.rows]], -1))
    if not alternative.any():
        return np.zeros(0, dtype=np.intp)
    nu, S = _joint_innovation(index, z, C_z, rows, landmarks)
    factor = cho_factor(S, lower=True, check_finite=False)
    y = cho_solve(factor, nu, check_finite=False).reshape(-1, 2)
    d2 = float(nu @ y.reshape(-1))
    nu = nu.reshape(-1, 2)
    # Only the diagonal blocks of Lambda of the rows with alternatives are needed.
    t_all = position[cands.rows[alternative]]
    wanted = np.unique(t_all)
    columns = np.zeros((len(rows), 2, len(wanted), 2))
    columns[wanted, :, np.arange(len(wanted)), :] = np.eye(2)
    Lambda = cho_solve(factor, columns.reshape(2 * len(rows), -1), check_finite=False)
    Lambda = Lambda.reshape(len(rows), 2, len(wanted), 2)[wanted, :, np.arange(len(wanted)), :]
    Sigma = np.linalg.inv(Lambda)
    Sigma_y = (Sigma @ y[wanted, :, None])[..., 0]
    mean = nu[wanted] - Sigma_y
    d2_rest = d2 - np.sum(y[wanted] * Sigma_y, axis=-1)
    t = np.searchsorted(wanted, t_all)
    swapped = cands.landmarks[alternative]
    S_swap = Sigma[t] - index.P_map[landmarks[t_all]] + index.P_map[swapped]
    d2_swap = d2_rest[t] + np.atleast_1d(mahalanobis_sq(
        z[rows[t_all]] - index.m_map[swapped], mean[t], S_swap))
    return np.unique(rows[t_all][d2_swap <= threshold])
