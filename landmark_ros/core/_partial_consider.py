"""
The update of a landmark with a view whose sensor bias is a consider state.

``partial.update_consider``. A sensor's bias is the same in all its views of a landmark:
split CI takes it as of unknown correlation with the landmark's error, and a robot
that sees a landmark from every side (where a range bias mostly cancels) keeps the
bias in full at every update: under-confident. The Schmidt-Kalman filter (S. F.
Schmidt, 1966; for sensor biases Novoselov, Herman, Gadaleta and Poore, "Mitigating
the effects of residual biases with Schmidt-Kalman filtering", FUSION 2005) keeps the
bias as a consider state: its estimate stays 0, but the cross-covariance ``c`` of the
landmark's error with it is carried, so the bias counts once. Private to ``core``:
``partial`` is the interface.

The model of a view: ``y = h(m) + l u + w``, ``u`` the sensor's bias in units of its
standard deviation (``N(0, 1)``), ``l = sqrt(R_bias)`` its loading, ``w`` the rest of
the view's error (independent noise ``R`` and the pose term, which split CI bounds as
before). With ``e = m_hat - m`` the landmark's error and ``c = Cov(e, u)``:

    S = H A H^T - 2 l H c + l^2 + a,       K = (A H^T - l c) / S
    e+ = (I - K H) e + K l u + K w,        c+ = (I - K H) c + K l

``A`` and ``a`` are split CI's (``update``). Taking out of ``u`` the part predicted by
``e`` (``u = G e + z``, ``G = c^T A^-1``) leaves a view ``h(m) + l G (m_hat - m)`` with
noise ``a + l^2 (1 - G c)`` independent of the prior: the plain update, gate and
iterations (``_iterate`` with ``shift = l G``) apply to it unchanged.
"""

from dataclasses import fields
from typing import Optional, Tuple

from landmark_ros.core import sensors
from landmark_ros.core._partial_model import GATED, linearise, TOO_CLOSE, UPDATED, Views
from landmark_ros.core._partial_update import (_gain, _iterate, _nonlinear_rows, _quadratic,
                                               ITERATE_THRESHOLD, UpdateResult, view_omega)
from landmark_ros.core.gating import chi2_threshold
import numpy as np
from numpy.typing import ArrayLike, NDArray


def update_consider(m: ArrayLike, P_m: ArrayLike, views: Views, P_m_dep: ArrayLike,
                    c: ArrayLike, gate_probability: float = 0.999,
                    iterate_threshold: Optional[float] = ITERATE_THRESHOLD
                    ) -> Tuple[UpdateResult, NDArray[np.float64]]:
    """
    Update landmarks with one view each, split CI, the view's bias a consider state.

    As ``update`` with ``split_covariance_intersection``, except that ``R_bias`` of a
    view is the variance of a bias whose cross-covariance ``c`` with the landmark's
    error is known (module docstring): it is left out of the view's dependent part
    and enters the gain and the covariance with its cross terms. With ``c = 0`` the
    bias is independent of the landmark: the same as ``update`` with ``R_bias`` moved
    into ``R``. A ``c`` larger than the prior allows (``c^T A^-1 c > 1``) is scaled
    down to fit.

    Parameters
    ----------
    m : array_like, shape (2,) or (N, 2) [m]
        Landmarks, one per view.
    P_m : array_like, shape (2, 2) or (N, 2, 2) [m^2]
        Their covariances.
    views : Views
        ``N`` views; ``R_bias`` is the variance of the consider bias.
    P_m_dep : array_like, shape (2, 2) or (N, 2, 2)
        The part of ``P_m`` of unknown correlation with the views' pose errors.
    c : array_like, shape (2,) or (N, 2)
        Cross-covariance of each landmark's error with its view's bias, in units of
        the bias's standard deviation [m].
    gate_probability : float
        In (0, 1): the 1-dof chi-square gate.
    iterate_threshold : float or None
        As ``update``.

    Returns
    -------
    result : UpdateResult
        As ``update``'s; ``P_m_dep`` is the updated part of unknown correlation and
        ``L`` is ``I - K H``, the map of a prior error independent of the view.
    c : ndarray, shape (N, 2)
        The cross-covariance after the update (unchanged where not ``UPDATED``).

    """
    n = len(views)
    m = np.broadcast_to(np.asarray(m, dtype=np.float64), (n, 2)).copy()
    P_m = np.broadcast_to(np.asarray(P_m, dtype=np.float64), (n, 2, 2)).copy()
    P_dep = np.broadcast_to(np.asarray(P_m_dep, dtype=np.float64), (n, 2, 2)).copy()
    c_prior = np.broadcast_to(np.asarray(c, dtype=np.float64), (n, 2)).copy()
    load = np.sqrt(views.R_bias)
    plain = Views._checked({f.name: getattr(views, f.name) for f in fields(Views)}
                           | {'R_bias': np.zeros(n)})
    xy = views.s[:, :2]
    too_close = np.hypot(*(m - xy).T) < sensors.MIN_RANGE
    lin = linearise(plain, np.where(too_close[:, None], xy + [1.0, 0.0], m))
    H = lin.J_h_m[:, 0, :]
    innovation = np.where(too_close, np.nan, lin.residual)
    S = _quadratic(H, P_m) - 2.0 * load * np.einsum('ni,ni->n', H, c_prior) + views.R_bias \
        + lin.R_eff
    d2 = innovation ** 2 / S
    status = np.where(too_close, TOO_CLOSE,
                      np.where(d2 <= chi2_threshold(1, gate_probability), UPDATED, GATED))
    P_ind = P_m - P_dep
    omega = view_omega(H, P_ind, P_dep, views.R + views.R_bias, lin.R_dep)
    A_dep = P_dep / omega[:, None, None]
    A = P_ind + A_dep
    c, G = _fitted(A, c_prior)
    shift = load[:, None] * G
    a_ind = views.R + views.R_bias * (1.0 - np.einsum('ni,ni->n', G, c))
    a_dep = lin.R_dep / (1.0 - omega)
    keep = status == UPDATED
    K = _gain(H - shift, A, a_ind + a_dep)
    m_new = np.where(keep[:, None], m + K * np.where(keep, innovation, 0.0)[:, None], m)
    iterations = keep.astype(np.int64)
    if iterate_threshold is not None and keep.any():
        b = _quadratic(H - shift, A)
        spread = np.sqrt(b * (a_ind + a_dep) / (b + a_ind + a_dep))
        rows = _nonlinear_rows(plain, m, m_new, H, spread, iterate_threshold, keep)
        if len(rows):
            def a_of(lin_i, local):
                return lin_i.R_dep / (1.0 - omega[rows[local]])
            m_it, taken = _iterate(plain[rows], m[rows], m_new[rows], A[rows], a_ind[rows],
                                   a_of, shift=shift[rows])
            lin_it = linearise(plain[rows], m_it)
            H[rows] = lin_it.J_h_m[:, 0, :]
            a_dep[rows] = lin_it.R_dep / (1.0 - omega[rows])
            K[rows] = _gain(H[rows] - shift[rows], A[rows], a_ind[rows] + a_dep[rows])
            m_new[rows], iterations[rows] = m_it, taken
    result, c_new = _posterior(m_new, P_m, P_dep, (P_ind, A_dep, a_dep), (H, K, load, c),
                               views, (innovation, S, d2, omega, status, iterations))
    return result, np.where(result.updated[:, None], c_new, c_prior)


def _fitted(A, c):
    """Return ``c`` scaled to ``c^T A^-1 c <= 1`` where it exceeds it, and ``A^-1 c``."""
    G = np.linalg.solve(A, c[:, :, None])[:, :, 0]
    excess = np.einsum('ni,ni->n', G, c)
    scale = np.where(excess > 1.0, 1.0 / np.sqrt(np.maximum(excess, 1.0)), 1.0)
    return c * scale[:, None], G * scale[:, None]


def _posterior(m_new, P_m, P_dep, parts, gain, views, report):
    """Return the update's result: the Joseph form with the bias's cross terms."""
    P_ind, A_dep, a_dep = parts
    H, K, load, c = gain
    keep = report[4] == UPDATED
    L = np.eye(2) - K[:, :, None] * H[:, None, :]
    KK = K[:, :, None] * K[:, None, :]
    Lc = np.einsum('nij,nj->ni', L, c)
    cross = load[:, None, None] * Lc[:, :, None] * K[:, None, :]
    new_ind = (L @ P_ind @ np.swapaxes(L, -1, -2)
               + KK * (views.R + views.R_bias)[:, None, None] + cross + np.swapaxes(cross, 1, 2))
    new_dep = L @ A_dep @ np.swapaxes(L, -1, -2) + KK * a_dep[:, None, None]
    new_ind = 0.5 * (new_ind + np.swapaxes(new_ind, -1, -2))
    new_dep = 0.5 * (new_dep + np.swapaxes(new_dep, -1, -2))
    P_new = np.where(keep[:, None, None], new_ind + new_dep, P_m)
    dep_new = np.where(keep[:, None, None], new_dep, P_dep)
    c_new = Lc + K * load[:, None]
    innovation, S, d2, omega, status, iterations = report
    return UpdateResult(m_new, P_new, dep_new, innovation, S, d2, omega, status, iterations,
                        np.where(keep[:, None, None], L, np.eye(2))), c_new
