"""
Joint compatibility branch and bound (JCBB) over the candidates of ``association``.

The rows of one message share the robot's pose error; ``jcbb`` pairs them with the
map's landmarks so that the stacked innovations pass one joint chi-square gate, with
the scan's joint covariance ``C_z`` from ``association.scan_covariance``. The symbols
are those of ``association``.

Sources
-------
- J. Neira and J. D. Tardos, "Data association in stochastic mapping using the joint
  compatibility test", IEEE Transactions on Robotics and Automation 17(6), 890-897, 2001.
- The fallback assignment: ``association.global_nearest_neighbour`` (Bar-Shalom and
  Fortmann, 1988).

"""

from landmark_ros.core.arrays import as_vectors
from landmark_ros.core.association import (_gnn_pairs, _joint_thresholds, _result,
                                           Association, Candidates, DEFAULT_MAX_NODES,
                                           LandmarkIndex)
from landmark_ros.core.gating import mahalanobis_sq
import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_factor, cho_solve, cholesky, solve_triangular


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
