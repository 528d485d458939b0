"""
White innovations for change detection: a Kalman filter per landmark over its rows (ROS-free).

Page's test (``fuser.change_detection``) needs, under "the landmark has not moved", a
sequence of independent normalised innovations squared, chi-square with 2 degrees of
freedom. The map's own innovations are not that: the rows of one source are correlated
in time (calibrated on MRCLAM: 0.94 of the range variance, 0.64 of the bearing variance,
correlation time 8.3 s), a robot's rows share its pose and bias errors, and CI and
split CI inflate the map's covariance, which hides a move. ``ReferenceFilter`` keeps,
per confirmed landmark, the Kalman filter of the model the rows follow and hands the
test that filter's innovations, white and with their exact covariance whatever the
fusion method.

Model (per landmark; ``p`` its position [m], ``c_s`` the slowly varying error of
source ``s``, first-order Gauss-Markov)::

    z_k = p + c_s(t_k) + w_k,          w_k ~ N(0, W_k)
    c_s(t') = phi c_s(t) + u,          phi = exp(-(t' - t) / tau),
                                       u ~ N(0, (1 - phi^2) C_k)

with ``tau`` = ``noise_correlation_time_s``. A row's covariance splits into its white
part ``W`` and its correlated part ``C`` (``split_noise``): the independent part
``R_ind = P - P_dep`` splits along its principal axes, the major axis taken as the range
direction (true where the range noise exceeds range times the bearing noise, as for
MRCLAM's camera and the simulator's defaults), ``range_correlated_fraction`` of its
variance along it and ``bearing_correlated_fraction`` across it being correlated; the
dependent part ``P_dep`` (pose and bias terms, shared by a robot's rows) is correlated
as a whole. ``tau = 0`` makes every row white (``W = P``): the state is ``p`` alone and
the filter is the independent fusion (product of Gaussians) of the rows.

The state is ``x = (p, c_1, ..., c_S)``, one block per source seen (``2 + 2 S``
values; ``S = 0`` when ``tau = 0``). Per row, from source ``s``:

- predict ``c_s`` from its last row: ``x_c <- phi x_c``, its rows and columns of the
  covariance ``X`` times ``phi``, ``X_cc += (1 - phi^2) C`` (a source not seen yet:
  ``phi = 0``);
- innovation ``nu = z - p - c_s``, ``S = X_pp + X_pc + X_cp + X_cc + W``, the test's
  ``d2 = nu^T S^-1 nu``;
- update (standard Kalman filter, ``H = [I, .., I at c_s, ..]``) unless ``d2`` is above
  the clip of the test: a wild row, or a row after a move, does not pull the reference
  towards it.

The first row of a landmark starts its filter (``p = z``, ``X_pp = W + C``,
``X_pc = -C``, ``X_cc = C``: the posterior from a flat prior on ``p``) and gives no
``d2``. Rows are taken in arrival order; the rows of one batch are processed in waves
(the k-th row of every landmark together), vectorised over the landmarks.
"""

from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

from landmark_ros.core.arrays import (entries_2x2, inverse_2x2, mahalanobis_sq_2x2,
                                      symmetric_2x2, unique_inverse)
from landmark_ros.fusion import compiled
import numpy as np
from numpy.typing import NDArray


class NoiseModel(NamedTuple):
    """The time correlation of the rows' noise (``FuserConfig``, module notes)."""

    correlation_time_s: float = 0.0
    """``tau`` [s]; 0: white rows."""
    range_fraction: float = 0.0
    """Share of the range variance (the major axis of ``R_ind``) that is correlated."""
    bearing_fraction: float = 0.0
    """Share of the bearing variance (the minor axis) that is correlated."""


def split_noise(P: NDArray[np.float64], P_dep: NDArray[np.float64],
                model: NoiseModel) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the white and correlated parts ``W, C`` of rows' covariances (module notes).

    Parameters
    ----------
    P : ndarray, shape (N, 2, 2) [m^2]
        Total covariances.
    P_dep : ndarray, shape (N, 2, 2) [m^2]
        Their dependent parts.
    model : NoiseModel
        The correlation model.

    Returns
    -------
    tuple of ndarray, shape (N, 2, 2) each
        ``W + C = P``; ``W = P, C = 0`` when ``correlation_time_s`` is 0.

    """
    P = np.asarray(P, np.float64)
    if model.correlation_time_s <= 0.0:
        return P, np.zeros_like(P)
    P_dep = np.asarray(P_dep, np.float64)
    values, vectors = np.linalg.eigh(P - P_dep)           # ascending: minor, major
    shares = values * np.array([model.bearing_fraction, model.range_fraction])
    C = np.einsum('nij,nj,nkj->nik', vectors, shares, vectors) + P_dep
    return P - C, C


class ReferenceFilter:
    """
    The Kalman filter of each landmark's rows; its innovations feed the test (module notes).

    Parameters
    ----------
    model : NoiseModel
        The rows' time correlation.
    clip : float
        Rows whose ``d2`` is above it do not update the filter.

    """

    def __init__(self, model: NoiseModel, clip: float) -> None:
        self.model = model
        self.clip = float(clip)
        self.correlated = model.correlation_time_s > 0.0
        self.sources: Dict[str, int] = {}
        """Block of each source in the state (empty when the rows are white)."""
        self.slots: Dict[int, int] = {}
        """Row of each landmark's filter in ``x``, ``X``."""
        self.x = np.zeros((0, 2))
        """States, shape (L, D) [m]."""
        self.X = np.zeros((0, 2, 2))
        """Their covariances, shape (L, D, D) [m^2]."""
        self.last_ns = np.zeros((0, 0), np.int64)
        """Stamp of each landmark's last row per source, shape (L, S) [ns] (-1: none)."""
        self.live = np.zeros(0, bool)
        """Whether each row of ``x`` holds a filter (False: the next row starts one)."""
        self._free: List[int] = []

    def reset(self, ids: Sequence[int]) -> None:
        """Forget the filters of ``ids``: each starts again from its next row."""
        for landmark_id in ids:
            slot = self.slots.pop(int(landmark_id), None)
            if slot is not None:
                self._free.append(slot)
                self.live[slot] = False

    def clear(self) -> None:
        """Forget every filter."""
        self.reset(list(self.slots))

    def innovations(self, ids: NDArray[np.int64], z: NDArray[np.float64],
                    P: NDArray[np.float64], P_dep: NDArray[np.float64],
                    sources: Sequence[str], stamps: NDArray[np.int64],
                    groups: Optional[Tuple[NDArray[np.int64], NDArray[np.intp]]] = None
                    ) -> NDArray[np.float64]:
        """
        Take rows in arrival order; return their ``d2`` against their filters.

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            Landmark IDs (rows the test takes: confirmed landmarks).
        z : ndarray, shape (N, 2) [m]
            The rows.
        P, P_dep : ndarray, shape (N, 2, 2) [m^2]
            Their total covariances and dependent parts.
        sources : sequence of str, length N
            Their sources.
        stamps : ndarray of int, shape (N,) [ns]
            Their stamps.
        groups : tuple, optional
            ``core.arrays.unique_inverse(ids)``, when the caller has it.

        Returns
        -------
        ndarray, shape (N,)
            NaN for a row that started its landmark's filter.

        """
        ids = np.asarray(ids, np.int64)
        d2 = np.full(len(ids), np.nan)
        if not len(ids):
            return d2
        if not self.correlated:         # W = P
            unique, inverse = unique_inverse(ids) if groups is None else groups
            slots = np.array([self._slot(i) for i in unique.tolist()], np.int64)
            d2 = compiled.reference((self.x, self.X, self.live), slots[inverse], z,
                                    np.column_stack(entries_2x2(P)), self.clip)
            return self._white(ids, z, np.asarray(P, np.float64), slots) if d2 is None else d2
        W, C = split_noise(P, P_dep, self.model)
        blocks = np.array([self._block(str(name)) for name in sources], np.int64)
        order = np.argsort(ids, kind='stable')
        first = np.ones(len(ids), bool)
        first[1:] = ids[order][1:] != ids[order][:-1]
        starts = np.flatnonzero(first)
        rank = np.empty(len(ids), np.int64)
        counts = np.diff(np.append(starts, len(ids)))
        rank[order] = np.arange(len(ids)) - np.repeat(starts, counts)
        for wave in range(int(rank.max()) + 1):
            rows = np.flatnonzero(rank == wave)
            fresh = np.array([int(i) not in self.slots for i in ids[rows].tolist()], bool)
            slots = np.array([self._slot(int(i)) for i in ids[rows].tolist()], np.int64)
            if fresh.any():
                self._start(slots[fresh], rows[fresh], z, W, C, blocks, stamps)
            old = rows[~fresh]
            if len(old):
                d2[old] = self._step(slots[~fresh], old, z, W, C, blocks, stamps)
        return d2

    def _white(self, ids: NDArray[np.int64], z: NDArray[np.float64], W: NDArray[np.float64],
               slots: Optional[NDArray[np.int64]] = None) -> NDArray[np.float64]:
        """
        Return the ``d2`` of white rows, all at once (information form; module notes).

        Row ``k``'s prediction is the product of its landmark's prior and the rows before
        it that were taken: prefix sums of the rows' information. A row past the clip is
        not taken, which changes the rows after it: each pass drops the first such row
        of every landmark and sums again (one pass when no row is past the clip).
        (``compiled.reference`` runs the rows one by one instead, once it is loaded.)
        ``slots``: the filters of the distinct IDs in order, when the caller has them.
        """
        order = np.argsort(ids, kind='stable')
        first = np.ones(len(ids), bool)
        first[1:] = ids[order][1:] != ids[order][:-1]
        group = np.cumsum(first) - 1
        starts = np.flatnonzero(first)
        if slots is None:
            slots = np.array([self._slot(i) for i in ids[order][starts].tolist()], np.int64)
        fresh = ~self.live[slots]
        prior = np.zeros((len(starts), 5))       # information (a, b, c) and vector, per landmark
        old = slots[~fresh]
        if len(old):
            prior[~fresh, :3] = np.column_stack(inverse_2x2(*entries_2x2(self.X[old][:, :2, :2])))
            prior[~fresh, 3:] = _times(prior[~fresh, :3], self.x[old][:, :2])
        zs, Ws = z[order], entries_2x2(W[order])
        rows = np.empty((len(ids), 5))
        rows[:, :3] = np.column_stack(inverse_2x2(*Ws))
        rows[:, 3:] = _times(rows[:, :3], zs)
        starting = first & fresh[group]          # a fresh landmark's first row starts it
        taken = np.ones(len(ids), bool)
        while True:
            before = _prefix(rows * taken[:, None], starts, group, prior)
            before[starting, :3] = [1.0, 0.0, 1.0]        # no prior: any invertible value
            X = np.column_stack(inverse_2x2(*before[:, :3].T))
            nu = zs - _times(X, before[:, 3:])
            d2 = mahalanobis_sq_2x2(nu[:, 0], nu[:, 1], *(X + np.column_stack(Ws)).T)
            d2[starting] = np.nan
            wild = np.flatnonzero(taken & (d2 > self.clip))
            if not len(wild):
                break
            taken[wild[np.unique(group[wild], return_index=True)[1]]] = False
        last = np.append(starts[1:], len(ids)) - 1
        end = np.where(starting[last, None], 0.0, before[last]) + rows[last] * taken[last, None]
        X_end = np.column_stack(inverse_2x2(*end[:, :3].T))
        self.X[slots, :2, :2] = symmetric_2x2(*X_end.T)
        self.x[slots, :2] = _times(X_end, end[:, 3:])
        self.live[slots] = True
        out = np.empty(len(ids))
        out[order] = d2
        return out

    def _block(self, name: str) -> int:
        """Return the state block of a source (added to every filter when new)."""
        if not self.correlated:
            return -1
        if name not in self.sources:
            self.sources[name] = len(self.sources)
            L = len(self.x)
            self.x = np.concatenate([self.x, np.zeros((L, 2))], axis=1)
            self.X = np.pad(self.X, ((0, 0), (0, 2), (0, 2)))
            self.last_ns = np.pad(self.last_ns, ((0, 0), (0, 1)), constant_values=-1)
        return self.sources[name]

    def _slot(self, landmark_id: int) -> int:
        """Return the row of a landmark's filter (a free or new one if it has none)."""
        slot = self.slots.get(landmark_id)
        if slot is not None:
            return slot
        if self._free:
            slot = self._free.pop()
        else:
            slot = len(self.x)
            self.x = np.concatenate([self.x, np.zeros((1, self.x.shape[1]))])
            self.X = np.concatenate([self.X, np.zeros((1,) + self.X.shape[1:])])
            self.last_ns = np.concatenate([self.last_ns, np.full((1, self.last_ns.shape[1]),
                                                                 -1, np.int64)])
            self.live = np.append(self.live, False)
        self.slots[landmark_id] = slot
        return slot

    def _start(self, slots: NDArray[np.int64], rows: NDArray[np.intp], z: NDArray[np.float64],
               W: NDArray[np.float64], C: NDArray[np.float64], blocks: NDArray[np.int64],
               stamps: NDArray[np.int64]) -> None:
        """Start filters from one row each: the posterior from a flat prior on ``p``."""
        self.x[slots] = 0.0
        self.X[slots] = 0.0
        self.last_ns[slots] = -1
        self.x[slots, :2] = z[rows]
        self.X[slots, :2, :2] = W[rows] + C[rows]
        self.live[slots] = True
        if self.correlated:
            c = 2 + 2 * blocks[rows, None] + np.arange(2)             # (n, 2)
            s = slots[:, None, None]
            self.X[s, np.arange(2)[None, :, None], c[:, None, :]] = -C[rows]
            self.X[s, c[:, :, None], np.arange(2)[None, None, :]] = -C[rows]
            self.X[s, c[:, :, None], c[:, None, :]] = C[rows]
            self.last_ns[slots, blocks[rows]] = stamps[rows]

    def _step(self, slots: NDArray[np.int64], rows: NDArray[np.intp], z: NDArray[np.float64],
              W: NDArray[np.float64], C: NDArray[np.float64], blocks: NDArray[np.int64],
              stamps: NDArray[np.int64]) -> NDArray[np.float64]:
        """Predict, return ``d2`` and update the filters of one wave (distinct landmarks)."""
        x, X = self.x[slots], self.X[slots]
        n, D = x.shape
        H = np.zeros((n, 2, D))
        H[:, :, :2] = np.eye(2)
        if self.correlated:
            b = blocks[rows]
            last = self.last_ns[slots, b]
            dt = (stamps[rows] - last) * 1e-9
            phi = np.where(last < 0, 0.0, np.exp(-np.maximum(dt, 0.0)
                                                 / self.model.correlation_time_s))
            scale = np.ones((n, D))
            c = 2 + 2 * b[:, None] + np.arange(2)
            scale[np.arange(n)[:, None], c] = phi[:, None]
            x = x * scale
            X = X * scale[:, :, None] * scale[:, None, :]
            X[np.arange(n)[:, None, None], c[:, :, None], c[:, None, :]] += (
                (1.0 - phi ** 2)[:, None, None] * C[rows])
            H[np.arange(n)[:, None], np.arange(2)[None, :], c] = 1.0
            self.last_ns[slots, b] = stamps[rows]
        nu = z[rows] - np.einsum('nij,nj->ni', H, x)
        XH = np.einsum('nij,nkj->nik', X, H)                        # (n, D, 2)
        S = np.einsum('nij,njk->nik', H, XH) + W[rows]
        S_inv_nu = np.linalg.solve(S, nu[..., None])[..., 0]
        d2 = np.einsum('ni,ni->n', nu, S_inv_nu)
        take = d2 <= self.clip
        K = np.swapaxes(np.linalg.solve(S, np.swapaxes(XH, 1, 2)), 1, 2)  # (n, D, 2)
        x_new = x + np.einsum('nij,nj->ni', K, nu)
        X_new = X - np.einsum('nij,nkj->nik', K, XH)
        X_new = 0.5 * (X_new + np.swapaxes(X_new, 1, 2))
        self.x[slots] = np.where(take[:, None], x_new, x)
        self.X[slots] = np.where(take[:, None, None], X_new, X)
        return d2


def _prefix(values: NDArray[np.float64], starts: NDArray[np.intp], group: NDArray[np.intp],
            prior: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return, per row, ``prior`` of its group plus the ``values`` of its group before it."""
    total = np.cumsum(values, axis=0) - values                 # every row before, any group
    return prior[group] + total - total[starts][group]


def _times(M: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return symmetric 2x2 matrices given as columns ``(a, b, c)`` times 2-vectors."""
    return np.column_stack([M[:, 0] * v[:, 0] + M[:, 1] * v[:, 1],
                            M[:, 1] * v[:, 0] + M[:, 2] * v[:, 1]])
