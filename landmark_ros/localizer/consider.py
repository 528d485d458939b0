"""
The Schmidt-Kalman (consider) update against a map held fixed (ROS-free).

``correlation='consider'`` in ``LocalizerConfig``. A landmark's error in the map is the
same at every sighting of it. The plain update (``independent``) takes it as new each
time and grows over-confident the longer the robot uses the landmark; split CI (``update``)
takes it as of unknown correlation and pays at every update, inflating the prior by
``1 / w`` each time, so the filter ends under-confident when it updates often. The
Schmidt-Kalman filter (S. F. Schmidt, "Application of state-space methods to navigation
problems", Advances in Control Systems 3, 1966; for sensor biases, Novoselov, Herman,
Gadaleta and Poore, "Mitigating the effects of residual biases with Schmidt-Kalman
filtering", FUSION 2005) carries the landmarks as consider states: their estimates and
covariances stay the map's, but the cross-covariance of the robot's error with theirs is
kept, so a landmark's error is counted once however often it is seen.

Symbols
-------
x, P
    The robot's state and its covariance, (n,), (n, n) (``update``).
C
    Cross-covariance of the state's error with the errors of the landmarks used so far,
    shape (n, 2K): landmark ``k`` (its slot, ``ConsiderSlots``) in columns ``2k, 2k+1``.
    Zero columns for a landmark not seen yet: before its first use the robot's error is
    independent of the map's.
H, G, P_u
    For the stacked components of one update, the Jacobians with respect to the state
    (k, n) and to the U landmarks they see (k, 2U); their covariance (2U, 2U), block
    diagonal (the map gives one covariance per landmark).

The update, with ``C_u`` the columns of those landmarks:

    S = H P H^T + H C_u G^T + G C_u^T H^T + G P_u G^T + R
    K = (P H^T + C_u G^T) S^-1
    x <- x + K nu,   P <- P - K S K^T,   C <- C - K (H C + G P_u E)

``E`` placing the landmarks' columns among the K; the landmarks themselves do not change.
The prediction turns ``C`` with the motion: ``C <- F C`` (``motion.predict_cross``). The
rows are gated with the row's own ``S`` (cross terms included) and iterated as in
``update`` (Gauss-Newton, ``H`` and ``G`` relinearised at the iterate).

When it is exact, and what it leaves out
----------------------------------------
The map's errors must be independent of the robot's before its first sighting: a
surveyed map, or one built without this robot's pose estimates (for MRCLAM's fused map:
motion-capture poses). A map built from this robot's own sightings holds a share of the
sensor noise of the row being applied; with many sightings per landmark that share is
small (MRCLAM dataset 6: each robot against a map fused without its own sightings gives
the same pose ANEES within 0.04), but in the closed loop, where the map is built from
the localizers' poses, the correlation is large and unknown: use ``split_ci`` there. A
new map (``set_map``) keeps the columns of the landmarks it shares with the old one by
ID: the map is taken as fixed (a landmark that leaves the map leaves ``C``). Rows of
another robot keep split CI, and ``C`` goes through that update as the state's error
does (``C <- A C``, ``UpdateResult.A``): the other robot's error is taken as
uncorrelated with the map's.
"""

import math
from typing import Dict, Iterable, NamedTuple, Optional

from landmark_ros.localizer.update import (observe, pose_difference, row_test, stacked_blocks,
                                           stacked_components, UpdateResult, UpdateSettings,
                                           wrapped_innovation)
import numpy as np
from numpy.typing import NDArray


class ConsiderRows(NamedTuple):
    """The landmarks of an update's rows."""

    slots: NDArray[np.intp]
    """Each row's landmark slot (``ConsiderSlots``), shape (N,)."""
    m: NDArray[np.float64]
    """Their positions from the map [m], shape (N, 2)."""
    P_m: NDArray[np.float64]
    """Their covariances [m^2], shape (N, 2, 2)."""


class ConsiderSlots:
    """Slots of the consider landmarks by ID, in the order of first use (``C``'s columns)."""

    def __init__(self) -> None:
        self._slot: Dict[int, int] = {}

    def slots(self, ids: NDArray[np.int64]) -> NDArray[np.intp]:
        """Return the slot of each ID (N,), taking the next free one for a new ID."""
        return np.array([self._slot.setdefault(int(i), len(self._slot)) for i in ids],
                        np.intp)

    @property
    def width(self) -> int:
        """Return the columns of ``C``: twice the landmarks with a slot."""
        return 2 * len(self._slot)

    def retain(self, ids: Iterable[int]) -> NDArray[np.intp]:
        """
        Keep the slots of the landmarks in ``ids`` only, renumbered in their order.

        Returns the columns of an old ``C`` that make the new one (``select``): a
        landmark that left the map leaves ``C``, which stays as wide as the map.
        """
        keep = {int(i) for i in ids}
        kept = sorted((slot, i) for i, slot in self._slot.items() if i in keep)
        self._slot = {i: k for k, (_, i) in enumerate(kept)}
        return (2 * np.array([slot for slot, _ in kept], np.intp)[:, None]
                + np.arange(2)).ravel()


def select(C: Optional[NDArray[np.float64]],
           columns: NDArray[np.intp]) -> Optional[NDArray[np.float64]]:
    """Return the ``columns`` of ``C`` (n, w), zero where ``C`` is narrower (None: None)."""
    if C is None:
        return None
    return widen(C, len(C), int(columns.max()) + 1 if len(columns) else 0)[:, columns]


def widen(C: Optional[NDArray[np.float64]], n: int, width: int) -> NDArray[np.float64]:
    """Return ``C`` (n, w) with zero columns up to ``width`` (None: all zero)."""
    if C is None:
        return np.zeros((n, width))
    if C.shape[1] >= width:
        return C
    return np.pad(C, ((0, 0), (0, width - C.shape[1])))


def _stack(x, m, rows, comps, landmark, count):
    """Return ``h`` (k,), ``H`` (k, n) and ``G`` (k, 2U) of the stacked components."""
    h, J_z_x, J_z_m = observe(x, m[rows])
    k = np.arange(len(rows))
    G = np.zeros((len(rows), 2 * count))
    G[k, 2 * landmark] = J_z_m[k, comps, 0]
    G[k, 2 * landmark + 1] = J_z_m[k, comps, 1]
    return h[k, comps], J_z_x[k, comps], G


def _gate(x, P, C, landmarks, z, R, kind, settings):
    """Return each row's test with the cross terms: ``d2`` (N,), passed (N,)."""
    slots, m, P_m = landmarks
    h, J_z_x, J_z_m = observe(x, m)
    C_rows = C.reshape(len(x), -1, 2)[:, slots, :].transpose(1, 0, 2)     # (N, n, 2)
    cross = J_z_x @ C_rows @ J_z_m.transpose(0, 2, 1)
    S = (J_z_x @ P @ J_z_x.transpose(0, 2, 1) + cross + cross.transpose(0, 2, 1)
         + J_z_m @ P_m @ J_z_m.transpose(0, 2, 1) + R)
    return row_test(z - h, S, kind, settings)


def update_consider(x: NDArray[np.float64], P: NDArray[np.float64],
                    C: Optional[NDArray[np.float64]], landmarks: ConsiderRows,
                    z: NDArray[np.float64], R: NDArray[np.float64], kind: NDArray[np.int64],
                    settings: UpdateSettings) -> UpdateResult:
    """
    Update the state from N landmark sightings with the landmarks as consider states.

    Parameters
    ----------
    x, P : ndarray, shapes (n,), (n, n)
        Prior state and covariance (``update``).
    C : ndarray, shape (n, w), or None
        Cross-covariance with the consider landmarks (module docstring); None: zero.
    landmarks : ConsiderRows
        Each row's landmark: its slot, position [m] and covariance [m^2] from the map.
    z : ndarray, shape (N, 2)
        Observations (range [m], bearing [rad]); the unused component of a partial row is
        ignored.
    R : ndarray, shape (N, 2, 2)
        Sensor noise, independent of the pose and the map.
    kind : ndarray of int, shape (N,)
        ``update.RANGE_BEARING``, ``RANGE`` or ``BEARING`` per row.
    settings : UpdateSettings
        Gates and iteration.

    Returns
    -------
    UpdateResult
        With ``C`` (n, max(w, 2 (largest slot + 1))); ``omega`` 1.

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to the pose.

    """
    slots, m, P_m = landmarks
    slots = np.asarray(slots, np.intp)
    C = widen(C, len(x), 2 * (int(slots.max()) + 1) if len(slots) else 0)
    z = np.where(np.isfinite(z), z, 0.0)
    _, passed = _gate(x, P, C, ConsiderRows(slots, m, P_m), z, R, kind, settings)
    if not passed.any():
        return UpdateResult(x, P, passed, ~passed, math.nan, 0, 1.0, 0, None, C)
    idx = np.flatnonzero(passed)
    rows, comps = stacked_components(kind[idx])
    rows_g = idx[rows]
    used_slots, first, landmark = np.unique(slots[idx], return_index=True, return_inverse=True)
    cols = (2 * used_slots[:, None] + np.arange(2)).ravel()
    C_u = C[:, cols]
    P_u = np.zeros((len(cols), len(cols)))
    for j, row in enumerate(idx[first]):
        P_u[2 * j:2 * j + 2, 2 * j:2 * j + 2] = P_m[row]
    R_s = stacked_blocks(R[idx], rows, comps)
    z_s = z[rows_g, comps]
    pieces = (m, rows_g, comps, landmark[rows], len(used_slots))
    h0, H0, G0 = _stack(x, *pieces)
    x_i, h_i, H_i, G_i, iterations = x, h0, H0, G0, 0
    while True:
        PHt = P @ H_i.T + C_u @ G_i.T
        S = H_i @ PHt + G_i @ (C_u.T @ H_i.T + P_u @ G_i.T) + R_s
        K = np.linalg.solve(S, PHt.T).T
        x_next = x + K @ (wrapped_innovation(z_s, h_i, comps) - H_i @ pose_difference(x, x_i))
        x_next[2] = (x_next[2] + math.pi) % (2.0 * math.pi) - math.pi
        iterations += 1
        h_next, H_next, G_next = _stack(x_next, *pieces)
        error = np.abs(wrapped_innovation(h_next, h_i + H_i @ pose_difference(x_next, x_i), comps))
        H_f, G_f = H_i, G_i
        x_i, h_i, H_i, G_i = x_next, h_next, H_next, G_next
        if (iterations >= settings.max_iterations
                or np.all(error <= settings.iterate_threshold * np.sqrt(np.diag(S)))):
            break
    D = H_f @ C
    D[:, cols] += G_f @ P_u
    P_new = P - K @ S @ K.T
    S0 = H0 @ (P @ H0.T + C_u @ G0.T) + G0 @ (C_u.T @ H0.T + P_u @ G0.T) + R_s
    nu0 = wrapped_innovation(z_s, h0, comps)
    nis = float(nu0 @ np.linalg.solve(S0, nu0))
    return UpdateResult(x_i, 0.5 * (P_new + P_new.T), passed, ~passed, nis, len(rows), 1.0,
                        iterations, np.eye(len(x)) - K @ H_f, C - K @ D)
