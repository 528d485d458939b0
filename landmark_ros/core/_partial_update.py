"""
EKF updates of a landmark with views (``partial.update``): plain, CI, split CI.

One view at a time, each gated on its 1-dof innovation; CI and split CI find the
weight omega that minimises the posterior determinant along a scalar direction.
Where the model is not linear over the step, the update iterates (iterated EKF,
Gauss-Newton on the posterior: ``ITERATE_THRESHOLD``). Private to ``core``:
``partial`` is the interface.
"""

from dataclasses import dataclass, replace
from typing import Optional

from landmark_ros.core import sensors
from landmark_ros.core._partial_model import (_OMEGA_STEPS, BEARING, GATED, linearise,
                                              METHODS, observe_views, OMEGA_EDGE, TOO_CLOSE,
                                              UPDATED, Views)
from landmark_ros.core.gating import chi2_threshold
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
from numpy.typing import ArrayLike, NDArray

_linearise = linearise   # _iterate's model may add a shift to it

_ROOT_BRACKET = 1e-15
"""``view_omega`` stops an element's search once its bracket is narrower: a few
rounding errors of omega, so a batch gives its rows' single-call weights to about 1e-15."""

ITERATE_THRESHOLD = 0.1
"""The update iterates where the linearisation error of the EKF step,
``|h(m1) - h(m0) - H0 (m1 - m0)|`` (the part of the change of the predicted view the
first-order model misses), exceeds this fraction of the posterior standard deviation
of the predicted view, ``sqrt(b a / (b + a))`` with ``b = H0 A H0^T`` and ``a`` the
view's variance (the localizer's update compares the same error with the
innovation's ``sqrt(b + a)``; a view far more precise than the landmark makes the
posterior, not the innovation, the scale the error must be small against). Below it
the update's first-order error is under a tenth of the spread it leaves, and one
linearisation is as good as the data."""

MAX_ITERATIONS = 10
"""Most linearisations of an iterated update (the first is the EKF step)."""

_CONVERGED = 1e-8
"""Iterations stop when a step's squared Mahalanobis length under the prior is below."""


@dataclass(frozen=True)
class UpdateResult:
    """
    The result of ``update`` for ``N`` (landmark, view) pairs.

    Attributes
    ----------
    m : ndarray, shape (N, 2) [m]
        Updated landmarks (unchanged where not ``UPDATED``).
    P_m : ndarray, shape (N, 2, 2) [m^2]
        Updated covariances.
    P_m_dep : ndarray, shape (N, 2, 2) [m^2]
        Their dependent parts.
    innovation : ndarray, shape (N,)
        ``y - h(m)`` before the update, bearings wrapped; NaN where ``TOO_CLOSE``.
    S : ndarray, shape (N,)
        ``H P_m H^T + R_eff``.
    mahalanobis_sq : ndarray, shape (N,)
        ``innovation^2 / S``, compared with the 1-dof chi-square gate.
    omega : ndarray, shape (N,)
        Weight of the landmark in (split) covariance intersection; NaN for
        ``independent``.
    status : ndarray of int, shape (N,)
        ``UPDATED``, ``GATED`` or ``TOO_CLOSE`` (``UPDATE_STATUS_NAMES``).
    iterations : ndarray of int, shape (N,)
        Linearisations the update took: 1 for the plain (extended) step, more where
        it iterated (``ITERATE_THRESHOLD``), 0 where not ``UPDATED``.
    L : ndarray, shape (N, 2, 2)
        ``I - K H`` of the Joseph form (the identity where not ``UPDATED``): a part
        of the prior's covariance independent of the view leaves as ``L P L^T``.

    """

    m: NDArray[np.float64]
    P_m: NDArray[np.float64]
    P_m_dep: NDArray[np.float64]
    innovation: NDArray[np.float64]
    S: NDArray[np.float64]
    mahalanobis_sq: NDArray[np.float64]
    omega: NDArray[np.float64]
    status: NDArray[np.int64]
    iterations: NDArray[np.int64]
    L: Optional[NDArray[np.float64]] = None

    @property
    def updated(self) -> NDArray[np.bool_]:
        """Return a mask of the rows that were updated, shape (N,)."""
        return self.status == UPDATED


def _quadratic(H, P):
    """Return ``H P H^T`` for rows ``H`` (N, 2) and matrices ``P`` (N, 2, 2)."""
    return np.einsum('ni,nij,nj->n', H, P, H)


def _posterior_log_det_slope(omega, H, P_ind, P_dep, R_ind, R_dep):
    """Return d/d omega of ``log det`` of the split-CI posterior covariance."""
    w = omega[:, None, None]
    A = P_ind + P_dep / w
    dA = -P_dep / (w * w)
    det_A = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    trace = (A[:, 1, 1] * dA[:, 0, 0] + A[:, 0, 0] * dA[:, 1, 1]
             - A[:, 0, 1] * dA[:, 1, 0] - A[:, 1, 0] * dA[:, 0, 1]) / det_A
    v = 1.0 - omega
    a = R_ind + R_dep / v
    da = R_dep / (v * v)
    return trace + da / a - (_quadratic(H, dA) + da) / (_quadratic(H, A) + a)


def view_omega(H: NDArray[np.float64], P_m_ind: NDArray[np.float64], P_m_dep: NDArray[np.float64],
               R_ind: NDArray[np.float64], R_dep: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return the split-CI weight that minimises ``det`` of the updated covariance.

    The landmark's covariance becomes ``A = P_m_ind + P_m_dep / omega`` and the view's
    variance ``a = R_ind + R_dep / (1 - omega)``; the Kalman update with them gives
    ``det P+ = det(A) a / (H A H^T + a)``. Its logarithm is convex in omega (the
    posterior information ``A^-1 + H^T H / a`` is a sum of parallel sums of terms
    linear in omega, hence operator concave), so its derivative, in closed form, has
    one root: found in ``[OMEGA_EDGE, 1 - OMEGA_EDGE]`` by regula falsi (``_slope_root``),
    vectorised.
    An end is returned when the slope does not change sign there (for example a
    landmark without a dependent part: ``OMEGA_EDGE``). Covariance intersection is
    the case ``P_m_ind = 0``, ``R_ind = 0``. Source: split CI (Julier and Uhlmann,
    "General decentralized data fusion with covariance intersection", *Handbook of
    Multisensor Data Fusion*, 2001, ch. 12; Li, Nashashibi and Yang, "Split
    covariance intersection filter", IEEE T-ITS 14(4), 2013) with a scalar,
    rank-deficient observation in place of a full estimate.

    Parameters
    ----------
    H : ndarray, shape (N, 2)
        ``J_h_m`` rows.
    P_m_ind, P_m_dep : ndarray, shape (N, 2, 2)
        Independent and dependent parts of the landmark covariance.
    R_ind, R_dep : ndarray, shape (N,)
        Independent and dependent parts of the view's effective variance.

    Returns
    -------
    omega : ndarray, shape (N,)

    """
    n = H.shape[0]
    lo = np.full(n, OMEGA_EDGE)
    hi = np.full(n, 1.0 - OMEGA_EDGE)
    args = (H, P_m_ind, P_m_dep, R_ind, R_dep)
    with np.errstate(divide='ignore', invalid='ignore'):
        slope_lo = _posterior_log_det_slope(lo, *args)
        slope_hi = _posterior_log_det_slope(hi, *args)
        omega = np.where(slope_lo >= 0.0, lo, np.where(slope_hi <= 0.0, hi, 0.5))
        inside = (slope_lo < 0.0) & (slope_hi > 0.0)
        if inside.any():
            a, b = lo[inside], hi[inside]
            omega[inside] = _slope_root(tuple(x[inside] for x in args), a, b,
                                        a * (1.0 - a) * slope_lo[inside],
                                        b * (1.0 - b) * slope_hi[inside])
    return omega


def _slope_root(args, a, b, fa, fb):
    """
    Return the root in ``[a, b]`` of ``g(w) = w (1 - w) _posterior_log_det_slope(w, *args)``.

    ``fa = g(a) < 0 < fb = g(b)``. The factor keeps the same root and takes away the
    slope's ``1 / w`` and ``1 / (1 - w)`` poles at the ends, which leave regula falsi
    crawling. Regula falsi with the Illinois modification (Dowell and Jarratt, BIT 11,
    1971; superlinear: about 12 evaluations against bisection's 60), vectorised; an
    element stops once its bracket is below ``_ROOT_BRACKET`` (or its ``g`` is 0),
    all after ``_OMEGA_STEPS`` evaluations at most (then the bracket's middle).
    """
    a, b, fa, fb = a.copy(), b.copy(), fa.copy(), fb.copy()
    side = np.zeros(len(a))
    c = 0.5 * (a + b)
    done = np.zeros(len(a), bool)
    for _ in range(_OMEGA_STEPS):   # every element each time; a finished one is frozen
        new = (a * fb - b * fa) / (fb - fa)
        new = np.where((new > a) & (new < b), new, 0.5 * (a + b))
        fc = new * (1.0 - new) * _posterior_log_det_slope(new, *args)
        up, down = ~done & (fc > 0.0), ~done & ~(fc > 0.0)
        c = np.where(done, c, new)
        fb, fa = (np.where(up, fc, np.where(down & (side < 0.0), 0.5 * fb, fb)),
                  np.where(down, fc, np.where(up & (side > 0.0), 0.5 * fa, fa)))
        b, a = np.where(up, new, b), np.where(down, new, a)
        side = np.where(up, 1.0, np.where(down, -1.0, side))
        done |= (b - a < _ROOT_BRACKET) | (fc == 0.0)
        if done.all():
            return c
    return np.where(done, c, 0.5 * (a + b))


def _method_terms(method, H, P_m, P_ind, P_dep, lin, R_ind, omega):
    """Return omega and the dependent parts ``A_dep``, ``a_dep`` of ``A`` and ``a``."""
    n = len(H)
    if method == 'independent':
        return np.full(n, np.nan), P_dep, lin.R_dep
    if omega is None:
        if method == 'covariance_intersection':
            omega = view_omega(H, np.zeros_like(P_m), P_m, np.zeros(n), lin.R_eff)
        else:
            omega = view_omega(H, P_ind, P_dep, R_ind, lin.R_dep)
    omega = np.broadcast_to(np.asarray(omega, dtype=np.float64), (n,)).copy()
    if not np.all((omega > 0.0) & (omega < 1.0)):
        raise ValueError(f'omega must lie strictly between 0 and 1, got {omega}')
    return omega, _prior_dep(method, P_m, P_ind, P_dep, omega), _view_dep(method, lin,
                                                                          R_ind, omega)


def _prior_dep(method, P_m, P_ind, P_dep, omega):
    """Return the dependent part of the landmark's covariance ``A`` as the method sees it."""
    w = omega[:, None, None]
    if method == 'independent':
        return P_dep
    if method == 'covariance_intersection':
        return P_m / w - P_ind
    return P_dep / w


def _view_dep(method, lin, R_ind, omega):
    """Return the dependent part of the view's variance ``a`` as the method sees it."""
    if method == 'independent':
        return lin.R_dep
    if method == 'covariance_intersection':
        return lin.R_eff / (1.0 - omega) - R_ind
    return lin.R_dep / (1.0 - omega)


def _gain(H, A, a):
    """Return the gain ``K = A H^T / (H A H^T + a)``, shape (N, 2)."""
    return (A @ H[:, :, None])[:, :, 0] / (_quadratic(H, A) + a)[:, None]


def _iterate(views, m0, m1, A, R_ind, a_of, max_iterations=MAX_ITERATIONS, shift=None):
    """
    Iterate the update of rows whose EKF step ``m0 -> m1`` was not linear enough.

    Gauss-Newton on the posterior cost ``(m - m0)^T A^-1 (m - m0) + (y - h(m))^2 / a``,
    in the iterated EKF's form (Bell and Cathey, "The iterated Kalman filter update as
    a Gauss-Newton method", IEEE T-AC 38(2), 1993): relinearise ``h`` at the iterate
    ``m_i`` and take ``m_i+1 = m0 + K_i (y - h(m_i) - H_i (m0 - m_i))``. A step that
    raises the cost is halved (up to 5 times); a step that lands within
    ``sensors.MIN_RANGE`` of the sensor ends the row's iterations where it is.

    Parameters
    ----------
    views : Views
        ``N`` views.
    m0, m1 : ndarray, shape (N, 2) [m]
        Prior means and the EKF step's results (the first iterate).
    A : ndarray, shape (N, 2, 2)
        The prior covariances as the method sees them.
    R_ind : ndarray, shape (N,)
        Independent variances of the views.
    a_of : callable
        ``(Linearisation of rows k, k) -> a_dep`` of those rows, shape (len(k),): the
        dependent part of the view's variance at an iterate.
    max_iterations : int
        Most linearisations, the EKF step's included.
    shift : ndarray, shape (N, 2), optional
        ``g``: the model is ``h(m) + g (m0 - m)`` (a prior error correlated with the
        view's, taken out: ``partial.update_consider``); None: ``h``.

    Returns
    -------
    m : ndarray, shape (N, 2)
        The last iterates.
    iterations : ndarray of int, shape (N,)
        Linearisations taken per row (at least 2).

    """
    def linearise(v, x, rows=slice(None)):
        lin = _linearise(v, x)
        if shift is None:
            return lin
        g = shift[rows]
        return replace(lin, residual=lin.residual - np.einsum('ni,ni->n', g, m0[rows] - x),
                       J_h_m=lin.J_h_m - g[:, None, :])

    A_inv = np.linalg.solve(A, np.broadcast_to(np.eye(2), A.shape))
    everything = np.arange(len(m0))
    m = m1.copy()
    lin = linearise(views, m)
    current = (np.einsum('ni,nij,nj->n', m - m0, A_inv, m - m0)
               + lin.residual ** 2 / (R_ind + a_of(lin, everything)))
    active = np.ones(len(m), bool)
    iterations = np.ones(len(m), np.int64)
    for _ in range(max_iterations - 1):
        rows = np.flatnonzero(active)
        if not len(rows):
            break
        sub = views[rows]
        H = lin.J_h_m[rows, 0, :]
        K = _gain(H, A[rows], R_ind[rows] + a_of(lin, everything)[rows])
        target = m0[rows] + K * (lin.residual[rows] + np.einsum(
            'ni,ni->n', H, m[rows] - m0[rows]))[:, None]
        step = target - m[rows]
        iterations[rows] += 1
        accepted = np.zeros(len(rows), bool)
        for _ in range(6):
            trial = m[rows] + step
            near = np.hypot(*(trial - sub.s[:, :2]).T) < sensors.MIN_RANGE
            trial = np.where(near[:, None], m[rows], trial)
            lin_trial = linearise(sub, trial, rows)
            c = np.einsum('ni,nij,nj->n', trial - m0[rows], A_inv[rows], trial - m0[rows]) + (
                lin_trial.residual ** 2 / (R_ind[rows] + a_of(lin_trial, rows)))
            good = ~accepted & ~near & (c <= current[rows])
            m[rows[good]] = trial[good]
            current[rows[good]] = c[good]
            accepted |= good | near
            if accepted.all():
                break
            step = np.where(accepted[:, None], step, 0.5 * step)
        length = np.einsum('ni,nij,nj->n', step, A_inv[rows], step)
        active[rows[~accepted | (length <= _CONVERGED)]] = False
        lin = linearise(views, m)
    return m, iterations


def update(m: ArrayLike, P_m: ArrayLike, views: Views, P_m_dep: Optional[ArrayLike] = None,
           method: str = 'independent', gate_probability: float = 0.999,
           omega: Optional[ArrayLike] = None,
           iterate_threshold: Optional[float] = ITERATE_THRESHOLD) -> UpdateResult:
    """
    Update landmarks with one view each: the EKF with a scalar measurement.

    With ``H = J_h_m`` at ``m``, the innovation ``y - h(m)`` (bearings wrapped) and
    ``S = H P_m H^T + R_eff`` are gated with chi-square, 1 dof. Rows that pass are
    updated with ``K = A H^T / (H A H^T + a)``, ``m+ = m + K (y - h(m))`` and the
    Joseph form ``P+ = (I - K H) A (I - K H)^T + K a K^T`` (Bucy and Joseph, 1968;
    Bar-Shalom, Li and Kirubarajan, 2001, sec. 5.2.3), applied to the independent
    and the dependent parts separately. ``A`` and ``a`` depend on the method:

    ``independent``
        ``A = P_m``, ``a = R_eff`` (the plain EKF).
    ``covariance_intersection``
        ``A = P_m / omega``, ``a = R_eff / (1 - omega)`` (Julier and Uhlmann, ACC
        1997); the inflation is booked as dependent. With a scalar view the
        determinant-optimal omega ignores the view (omega near 1) unless
        ``H P_m H^T > 2 R_eff``.
    ``split_covariance_intersection``
        ``A = P_ind + P_m_dep / omega``, ``a = R_ind + R_dep / (1 - omega)``.

    omega minimises ``det P+`` (``view_omega``) unless given. Where the EKF step's
    linearisation error exceeds ``iterate_threshold`` standard deviations of the
    predicted view's posterior (``ITERATE_THRESHOLD``), the update iterates (``_iterate``: the
    iterated EKF, Gauss-Newton on the posterior, with the same ``A``, omega and the
    gate of the first linearisation) and the covariance is the Joseph form at the last
    iterate. Rows are independent pairs: a landmark seen by several views is updated
    by calling again (or by a loop over its views), not twice in one batch.

    Parameters
    ----------
    m : array_like, shape (2,) or (N, 2) [m]
        Landmarks, one per view (or one for all).
    P_m : array_like, shape (2, 2) or (N, 2, 2) [m^2]
        Their covariances.
    views : Views
        ``N`` views.
    P_m_dep : array_like, shape (2, 2) or (N, 2, 2), optional
        Dependent parts of ``P_m``; zero by default.
    method : str
        One of ``METHODS``.
    gate_probability : float
        In (0, 1): innovations beyond the chi-square quantile are ``GATED``.
    omega : float or array_like, shape () or (N,), optional
        Weight in (0, 1) for the intersections instead of the optimal one.
    iterate_threshold : float or None
        Linearisation error, in posterior standard deviations of the predicted view,
        above which the update iterates; 0 iterates every row, None never (the plain
        EKF).

    Returns
    -------
    UpdateResult

    Raises
    ------
    ValueError
        On an unknown method, a wrong shape, or ``omega`` outside (0, 1).

    """
    if method not in METHODS:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    n = len(views)
    m = np.broadcast_to(np.asarray(m, dtype=np.float64), (n, 2)).copy()
    P_m = np.broadcast_to(np.asarray(P_m, dtype=np.float64), (n, 2, 2)).copy()
    P_dep = (np.zeros((n, 2, 2)) if P_m_dep is None
             else np.broadcast_to(np.asarray(P_m_dep, dtype=np.float64), (n, 2, 2)).copy())
    threshold = chi2_threshold(1, gate_probability)
    xy = views.s[:, :2]
    too_close = np.hypot(*(m - xy).T) < sensors.MIN_RANGE
    lin = linearise(views, np.where(too_close[:, None], xy + [1.0, 0.0], m))
    H = lin.J_h_m[:, 0, :]
    innovation = np.where(too_close, np.nan, lin.residual)
    S = _quadratic(H, P_m) + lin.R_eff
    d2 = innovation ** 2 / S
    status = np.where(too_close, TOO_CLOSE, np.where(d2 <= threshold, UPDATED, GATED))
    P_ind = P_m - P_dep
    R_ind = views.R
    omega, A_dep, a_dep = _method_terms(method, H, P_m, P_ind, P_dep, lin, R_ind, omega)
    A = P_ind + A_dep
    K = _gain(H, A, R_ind + a_dep)
    keep = status == UPDATED
    m_new = np.where(keep[:, None], m + K * np.where(keep, innovation, 0.0)[:, None], m)
    iterations = keep.astype(np.int64)
    if iterate_threshold is not None and keep.any():
        b, a = _quadratic(H, A), R_ind + a_dep
        spread = np.sqrt(b * a / (b + a))      # posterior standard deviation of h

        def a_of(lin_i, rows):
            return _view_dep(method, lin_i, R_ind[rows], omega[rows])

        rows = _nonlinear_rows(views, m, m_new, H, spread, iterate_threshold, keep)
        if len(rows):
            m_it, taken = _iterate(views[rows], m[rows], m_new[rows], A[rows], R_ind[rows],
                                   lambda lin_i, local: a_of(lin_i, rows[local]))
            lin_it = linearise(views[rows], m_it)
            H[rows] = lin_it.J_h_m[:, 0, :]
            a_dep[rows] = a_of(lin_it, rows)
            K[rows] = _gain(H[rows], A[rows], R_ind[rows] + a_dep[rows])
            m_new[rows], iterations[rows] = m_it, taken
    L = np.eye(2) - K[:, :, None] * H[:, None, :]
    KK = K[:, :, None] * K[:, None, :]
    new_ind = L @ P_ind @ np.swapaxes(L, -1, -2) + KK * R_ind[:, None, None]
    new_dep = L @ A_dep @ np.swapaxes(L, -1, -2) + KK * a_dep[:, None, None]
    new_ind = 0.5 * (new_ind + np.swapaxes(new_ind, -1, -2))
    new_dep = 0.5 * (new_dep + np.swapaxes(new_dep, -1, -2))
    P_new = np.where(keep[:, None, None], new_ind + new_dep, P_m)
    dep_new = np.where(keep[:, None, None], new_dep, P_dep)
    return UpdateResult(m_new, P_new, dep_new, innovation, S, d2, omega, status, iterations,
                        np.where(keep[:, None, None], L, np.eye(2)))


def _nonlinear_rows(views, m, m_new, H, spread, threshold, updated):
    """
    Return the rows whose EKF step ``m -> m_new`` was not linear enough (``update``).

    The linearisation error ``|h(m_new) - h(m) - H (m_new - m)|`` (bearings wrapped)
    against ``threshold`` times ``spread``, the posterior standard deviation of the
    predicted view; rows not ``updated``, or whose step lands on the sensor, are not
    returned.
    """
    rows = np.flatnonzero(updated)
    sub = views[rows]
    step = m_new[rows] - m[rows]
    far = np.hypot(*(m_new[rows] - sub.s[:, :2]).T) >= sensors.MIN_RANGE
    moved = observe_views(sub, np.where(far[:, None], m_new[rows], m[rows]))
    change = moved - observe_views(sub, m[rows])
    change = np.where(sub.kind == BEARING, wrap_angle(change), change)
    error = np.abs(change - np.einsum('ni,ni->n', H[rows], step))
    return rows[far & (error > threshold * spread[rows])]
