"""
The EKF measurement update of a planar pose from landmark sightings (ROS-free).

Symbols
-------
x, P
    Robot pose ``(x, y, theta)`` in the map frame and its covariance, (3,), (3, 3); or
    the pose and the range scale error ``s`` (below), (4,), (4, 4), and its change with
    the bearing, (5,), (5, 5).
m, P_m
    Landmark positions and covariances from the map (or another robot's position and
    the xy block of its published covariance), (N, 2), (N, 2, 2).
z, R
    Observations ``(range, bearing)`` and their noise, (N, 2), (N, 2, 2).
kind
    Per row which components count: ``RANGE_BEARING`` (both), ``RANGE`` (range-only) or
    ``BEARING`` (bearing-only): the partial observations.
h, J_z_x, J_z_m
    Predicted observation ``h(x, m)`` and its Jacobians with respect to the pose and to
    the landmark (``landmark_ros.core.sensors.observe`` and ``observe_jacobians``).

Innovation covariance of a row: ``S = J_z_x P J_z_x^T + J_z_m P_m J_z_m^T + R``: the map's
uncertainty counts. Each row is gated alone (chi-square with 1 or 2 degrees of freedom);
the rows that pass are stacked and applied in one update.

The map is correlated with the pose
-----------------------------------
A fused map holds the robot's own earlier sightings, made from poses whose errors are
those of the current estimate in part; another robot's pose estimate has taken this
robot's information when they met. The errors of ``x`` and of ``m`` are then correlated
in an unknown way, and the plain update (``correlation='independent'``) is over-confident.
``correlation='split_ci'`` keeps it consistent for any such correlation: split covariance
intersection (Julier and Uhlmann 2001; in an EKF, Li and Nashashibi 2013) with the sensor
noise ``R`` as the independent part and the pose prior and the map term as the parts of
unknown correlation:

    P1 = P / w,   P2 = R + M / (1 - w),   M = J_z_m P_m J_z_m^T (block diagonal)

followed by the Kalman update of ``(x, P1)`` with the measurement of noise ``P2``;
``w`` in (0, 1) minimises the determinant of the updated covariance (nested grids).
For any joint covariance of ``x`` and ``m`` with those marginals, ``P1 + P2``-based
bounds hold (the CI inequality), so the result is an upper bound of the true
covariance. With a precise map (``M`` small against ``J P J^T``) the weight goes to 1
and the update to the plain EKF; it costs where the map is as uncertain as the pose.
Cooperative updates (Carrillo-Arce et al., IROS 2013, used covariance intersection on
MRCLAM) go through the same update with the other robot as the landmark.

Range scale state
-----------------
A camera that reads range from apparent size misreads it by a scale that is its own and
constant (``core.range_scale`` corrects the part all robots share; what is left differs
from robot to robot and lasts the whole run). Filtered as white or time-correlated noise
it is counted again at every sighting, and a forward-looking camera, whose landmarks are
all ahead, turns it into a position error along the heading that no number of sightings
removes. With ``x`` of 4 components the fourth is that relative error ``s``: a range reads
``d (1 + s)`` (``observe``), ``s`` constant between updates (``motion.predict_with``).
With 5 the fifth is its change with the bearing ``b`` [1/rad]: ``d (1 + s + s_b b)``, a
lens that reads landmarks on one side shorter than on the other (MRCLAM dataset 6:
robot 5's ranges 1.3 % short on its left, 0.7 % long on its right, the same in both
halves of the run), which a forward-looking camera turns into a sideways position
error.

Iterated update
---------------
After the first (EKF) step, the linearisation error of ``h`` at the new pose,
``|h(x1) - h(x0) - J (x1 - x0)|``, is compared with the innovation's standard deviation;
above ``iterate_threshold`` of it the Gauss-Newton iterations of the iterated EKF
(Bell and Cathey 1993) run, at most ``max_iterations``, relinearising ``h`` at each
iterate with the same ``P1``, ``P2``.
"""

from dataclasses import dataclass
import math
from typing import NamedTuple, Optional, Sequence, Tuple, Union

from landmark_ros.core import range_scale, sensors
import numpy as np
from numpy.typing import NDArray

RANGE_BEARING, RANGE, BEARING = 0, 1, 2
"""Kinds of rows: which components of ``z`` count."""


class SensorNoise(NamedTuple):
    """
    Sensor noise split by how it relates to the pose (``update``'s ``R``).

    ``R`` is independent of the pose and of the map; ``R_dep`` (per row) and
    ``R_shared`` (one error shared by every row of the update, the sensor bias) may be
    correlated with the pose in any way, through the sightings it was updated with
    before: with ``split_ci`` they join the map term ``M``.
    """

    R: NDArray[np.float64]
    """Independent noise, shape (N, 2, 2)."""
    R_dep: NDArray[np.float64]
    """Per-row noise of unknown correlation with the pose, shape (N, 2, 2)."""
    R_shared: Optional[NDArray[np.float64]] = None
    """Noise shared by all rows (fully correlated between them), shape (2, 2)."""


@dataclass
class UpdateResult:
    """What one update did."""

    x: NDArray[np.float64]
    """Updated state, shape (n,) (as ``x``)."""
    P: NDArray[np.float64]
    """Updated covariance, shape (n, n)."""
    used: NDArray[np.bool_]
    """Rows applied, shape (N,)."""
    gated: NDArray[np.bool_]
    """Rows outside the chi-square gate, shape (N,)."""
    nis: float
    """Normalised innovation squared of the applied rows (NaN if none)."""
    dof: int
    """Its degrees of freedom (applied components)."""
    omega: float
    """Split-CI weight of the pose prior (1: plain EKF)."""
    iterations: int
    """Gauss-Newton iterations (1: plain EKF step)."""
    A: Optional[NDArray[np.float64]] = None
    """``I - K H`` of the last linearisation, shape (n, n) (None: nothing applied): the
    state's error after the update is ``A`` times the one before plus the gain times the
    measurement's (``localizer.consider`` carries cross-covariances through it)."""
    C: Optional[NDArray[np.float64]] = None
    """Updated cross-covariance with the consider states, shape (n, 2K)
    (``localizer.consider``; None: none)."""


@dataclass(frozen=True)
class UpdateSettings:
    """How the update gates, weighs and iterates (from ``LocalizerConfig``)."""

    gate_1: float
    """Chi-square threshold of a partial row (1 dof)."""
    gate_2: float
    """Chi-square threshold of a range-bearing row (2 dof)."""
    correlation: str = 'split_ci'
    iterate_threshold: float = 0.1
    max_iterations: int = 5
    landmark_correlation: str = 'independent'
    """``independent`` (the landmarks of one update have independent errors) or
    ``unknown`` (correlated in any way: ``landmark_bound``)."""


def correct_ranges(z: NDArray[np.float64], kind: NDArray[np.int64],
                   R: Optional[NDArray[np.float64]], coeffs: Sequence[float],
                   per_m: float) -> Tuple[NDArray[np.float64], Optional[NDArray[np.float64]]]:
    """
    Return readings with the range scale error removed (``core.range_scale``).

    Only finite ``RANGE_BEARING`` rows are corrected: a range-only row has no bearing to
    correct with; a row outside the model (scale below ``range_scale.MIN_SCALE``: a
    bearing far outside the calibrated field of view) is left as it is. With ``coeffs``
    zero and ``per_m`` 0 nothing changes.

    Parameters
    ----------
    z : ndarray, shape (N, 2)
        Readings (range [m], bearing [rad]).
    kind : ndarray of int, shape (N,)
        Row kinds.
    R : ndarray, shape (N, 2, 2), optional
        Noise of the readings, propagated as ``J R J^T`` on the corrected rows; None
        stays None (the caller's noise model describes the corrected reading).
    coeffs : sequence of 3 float
        ``(c0, c1, c2)`` of ``range_scale.scale``.
    per_m : float
        Its ``k`` [1/m].

    Returns
    -------
    z : ndarray, shape (N, 2)
    R : ndarray, shape (N, 2, 2), or None

    """
    z = np.asarray(z, dtype=np.float64)
    if range_scale.is_identity(coeffs, per_m):
        return z, None if R is None else np.asarray(R, dtype=np.float64)
    rows = (kind == RANGE_BEARING) & np.all(np.isfinite(z), axis=1)
    rows[rows] = range_scale.scale(z[rows], coeffs, per_m) >= range_scale.MIN_SCALE
    if not rows.any():
        return z, None if R is None else np.asarray(R, dtype=np.float64)
    z = z.copy()
    if R is None:
        z[rows], _ = range_scale.correct(z[rows], coeffs, per_m)
        return z, None
    R = np.array(R, dtype=np.float64)
    z[rows], R[rows] = range_scale.correct_with_noise(z[rows], R[rows], coeffs, per_m)
    return z, R


def sensor_noise(config, z: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return the noise of observations ``z`` (N, 2) under ``config``, shape (N, 2, 2).

    ``config`` is a ``LocalizerConfig`` (its ``range_stddev*`` and ``bearing_stddev``):
    the range variance grows with the range (``sensors.range_noise_variance``; a
    non-finite range counts as 0), the bearing's is constant; no cross term.
    """
    r = np.nan_to_num(z[:, 0])
    R = np.zeros((len(z), 2, 2))
    R[:, 0, 0] = sensors.range_noise_variance(r, config.range_stddev ** 2,
                                              config.range_stddev_per_m ** 2,
                                              config.range_stddev_per_m2 ** 2)
    R[:, 1, 1] = config.bearing_stddev ** 2
    return R


def row_noise(R: NDArray[np.float64], parts: Tuple[NDArray[np.float64], NDArray[np.float64]],
              R_bias: NDArray[np.float64], shared: Optional[NDArray[np.float64]],
              shared_bias: Optional[NDArray[np.float64]],
              dependent: bool) -> Union[NDArray[np.float64], SensorNoise]:
    """
    Return the noise of a batch's rows with its time-correlated part and the bias.

    ``count`` (``dependent`` False): one array, the correlated part times ``shared`` (the
    sightings of the row's landmark sharing its error) and ``R_bias`` times
    ``shared_bias`` (the sightings of any landmark), all taken as independent.
    ``dependent``: a ``SensorNoise``, the white part independent, the correlated part
    (once) and the bias (one error for every row) of unknown correlation with the pose.

    Parameters
    ----------
    R : ndarray, shape (N, 2, 2)
        Sensor noise of the rows.
    parts : (ndarray, ndarray), each shape (2, 2)
        Entry-wise factors of ``R``: its white and its time-correlated part.
    R_bias : ndarray, shape (2, 2)
        Covariance of the sensor bias (zero: none).
    shared, shared_bias : ndarray, shape (N,), optional
        The counts of ``count`` (None: 1, no bias term).
    dependent : bool
        Which of the two forms.

    """
    white, correlated = parts
    if dependent:
        return SensorNoise(R * white, R * correlated, R_bias if R_bias.any() else None)
    n = 1.0 if shared is None else shared[:, None, None]
    out = R * (white + correlated * n)
    if shared_bias is not None and R_bias.any():
        out = out + R_bias * shared_bias[:, None, None]
    return out


def stacked_components(kind: NDArray[np.int64]) -> Tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Return the row index and component (0 range, 1 bearing) of each used scalar (k,)."""
    rows, comps = [], []
    for i, k in enumerate(kind):
        if k != BEARING:
            rows.append(i)
            comps.append(0)
        if k != RANGE:
            rows.append(i)
            comps.append(1)
    return np.array(rows, np.intp), np.array(comps, np.intp)


def wrapped_innovation(z: NDArray[np.float64], h: NDArray[np.float64],
                       comp: NDArray[np.intp]) -> NDArray[np.float64]:
    """Return ``z - h`` (k,) of stacked components, the bearings (``comp`` 1) wrapped."""
    nu = z - h
    bearing = comp == 1
    nu[bearing] = (nu[bearing] + math.pi) % (2.0 * math.pi) - math.pi
    return nu


def observe(x: NDArray[np.float64], m: NDArray[np.float64]
            ) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the predicted readings of landmarks and their Jacobians, with the range scale.

    ``x`` is the pose ``(x, y, theta)``, or the pose and a range scale error ``s``, and
    its change with the bearing ``s_b`` (module docstring, range scale state): the range
    reads ``d (1 + s + s_b b)``, ``d`` the distance and ``b`` the bearing
    (``sensors.observe``); the bearing does not depend on them.

    Parameters
    ----------
    x : ndarray, shape (3,), (4,) or (5,)
        Pose [m, m, rad], optionally the scale error [1] and its change with the
        bearing [1/rad].
    m : ndarray, shape (N, 2)
        Landmark positions [m].

    Returns
    -------
    h : ndarray, shape (N, 2)
        Range [m] and bearing [rad].
    J_z_x : ndarray, shape (N, 2, len(x))
        Jacobian with respect to ``x``.
    J_z_m : ndarray, shape (N, 2, 2)
        Jacobian with respect to the landmark.

    """
    h = sensors.observe(x[:3], m)
    J_z_p, J_z_m = sensors.observe_jacobians(x[:3], m)
    if len(x) == 3:
        return h, J_z_p, J_z_m
    d, b = h[:, 0], h[:, 1]
    s_b = x[4] if len(x) > 4 else 0.0
    g = 1.0 + x[3] + s_b * b
    J_z_x = np.zeros((len(m), 2, len(x)))
    J_z_x[:, :, :3] = J_z_p
    J_z_x[:, 0, :3] = g[:, None] * J_z_p[:, 0] + (s_b * d)[:, None] * J_z_p[:, 1]
    J_z_x[:, 0, 3] = d
    J_z_m = J_z_m.copy()
    J_z_m[:, 0] = g[:, None] * J_z_m[:, 0] + (s_b * d)[:, None] * J_z_m[:, 1]
    if len(x) > 4:
        J_z_x[:, 0, 4] = d * b
    h = h.copy()
    h[:, 0] = d * g
    return h, J_z_x, J_z_m


def _row_gate(x, P, m, P_m, z, R, kind, settings):
    """Return the per-row chi-square test: d2 (N,), passed (N,); ``R`` the total noise."""
    h, J_z_x, J_z_m = observe(x, m)
    S = J_z_x @ P @ J_z_x.transpose(0, 2, 1) + J_z_m @ P_m @ J_z_m.transpose(0, 2, 1) + R
    return row_test(z - h, S, kind, settings)


def row_test(nu: NDArray[np.float64], S: NDArray[np.float64], kind: NDArray[np.int64],
             settings: UpdateSettings) -> Tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """
    Return each row's chi-square test: ``d2`` (N,) and whether it passed (N,).

    ``nu`` (N, 2) are the innovations (the bearing is wrapped here), ``S`` (N, 2, 2)
    their covariances; a partial row counts its one component (1 dof).
    """
    nu = np.array(nu, dtype=np.float64)
    nu[:, 1] = (nu[:, 1] + math.pi) % (2.0 * math.pi) - math.pi
    d2 = np.empty(len(nu))
    full = kind == RANGE_BEARING
    if full.any():
        solved = np.linalg.solve(S[full], nu[full][..., None])[..., 0]
        d2[full] = np.einsum('ni,ni->n', nu[full], solved)
    for k, c in ((RANGE, 0), (BEARING, 1)):
        sel = kind == k
        if sel.any():
            d2[sel] = nu[sel, c] ** 2 / S[sel, c, c]
    threshold = np.where(full, settings.gate_2, settings.gate_1)
    return d2, d2 <= threshold


def _stack(x, m, rows, comps):
    """Return ``h`` (k,) and ``J_z_x`` (k, n) of the scalar components at state ``x``."""
    h, J_z_x, _ = observe(x, m[rows])
    k = np.arange(len(rows))
    return h[k, comps], J_z_x[k, comps]


def stacked_blocks(M_rows: NDArray[np.float64], rows: NDArray[np.intp],
                   comps: NDArray[np.intp]) -> NDArray[np.float64]:
    """Return the (k, k) block-diagonal matrix of per-row 2x2 blocks at the components."""
    same = rows[:, None] == rows[None, :]
    return np.where(same, M_rows[rows[:, None], comps[:, None], comps[None, :]], 0.0)


def landmark_bound(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return per-row map terms that bound the rows' map errors for any correlation.

    The landmarks of a fused map share the errors of the poses they were placed from,
    so the stacked map errors of one update are correlated in a way nobody tracks. For
    any weights ``v_i > 0`` summing to one, ``Cov(stacked) <= blockdiag(M_i / v_i)``
    (Cauchy-Schwarz, the covariance intersection inequality); with ``v_i``
    proportional to ``c_i = sqrt(trace(M_i))`` it is ``M_i C / c_i``, ``C = sum c_i``.
    A row without map term (``c_i = 0``) keeps zero. One row is returned unchanged.

    Parameters
    ----------
    M : ndarray, shape (N, 2, 2)
        Map terms ``J_z_m P_m J_z_m^T`` of the rows.

    Returns
    -------
    ndarray, shape (N, 2, 2)

    """
    if len(M) < 2:
        return M
    c = np.sqrt(np.maximum(M[:, 0, 0] + M[:, 1, 1], 0.0))
    scale = np.divide(c.sum(), c, out=np.zeros_like(c), where=c > 0.0)
    return M * scale[:, None, None]


def _posterior_logdets(P_inv, H, R_s, M_s, w):
    """Return ``-log det`` of the information after the update, for each weight ``w`` (K,)."""
    W = w[:, None, None]
    A = R_s[None] + M_s[None] / (1.0 - W)
    H_k = np.broadcast_to(H, (len(w),) + H.shape)
    info = W * P_inv[None] + H.T[None] @ np.linalg.solve(A, H_k)
    return -np.linalg.slogdet(info)[1]


def split_ci_weight(P: NDArray[np.float64], H: NDArray[np.float64], R_s: NDArray[np.float64],
                    M_s: NDArray[np.float64], points: int = 16, rounds: int = 3) -> float:
    """
    Return the split-CI weight ``w`` of the pose prior (module docstring).

    Minimises ``log det`` of the updated covariance over ``w`` in ``(0, 1)``: a grid of
    ``points`` weights (evenly spaced in ``log(w / (1 - w))`` from -9 to 14), then
    ``rounds`` finer grids between the neighbours of the best, each evaluated in one
    batched call. ``M_s`` near zero gives ``w`` near 1.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        State covariance.
    H : ndarray, shape (k, n)
        ``J_z_x`` of the stacked components.
    R_s, M_s : ndarray, shape (k, k)
        Sensor noise and map term of the stacked components.
    points : int
        Weights per grid.
    rounds : int
        Refinements after the first grid.

    """
    P_inv = np.linalg.inv(P)
    logits = np.linspace(-9.0, 14.0, points)
    for _ in range(rounds + 1):
        w = 1.0 / (1.0 + np.exp(-logits))
        best = int(np.argmin(_posterior_logdets(P_inv, H, R_s, M_s, w)))
        low, high = logits[max(best - 1, 0)], logits[min(best + 1, points - 1)]
        logits = np.linspace(low, high, points)
    return float(w[best])


def update(x: NDArray[np.float64], P: NDArray[np.float64], m: NDArray[np.float64],
           P_m: NDArray[np.float64], z: NDArray[np.float64],
           R: Union[NDArray[np.float64], SensorNoise], kind: NDArray[np.int64],
           settings: UpdateSettings) -> UpdateResult:
    """
    Update the pose from N landmark sightings: gate each row, then one (iterated) update.

    Parameters
    ----------
    x : ndarray, shape (3,), (4,) or (5,)
        Prior pose, optionally with the range scale states (module docstring).
    P : ndarray, shape (n, n), n = len(x)
        Its covariance.
    m : ndarray, shape (N, 2)
        Landmark positions [m].
    P_m : ndarray, shape (N, 2, 2)
        Their covariances [m^2].
    z : ndarray, shape (N, 2)
        Observations (range [m], bearing [rad]); the unused component of a partial row
        is ignored (may be NaN).
    R : ndarray, shape (N, 2, 2), or SensorNoise
        Sensor noise: an array is independent of the pose; a ``SensorNoise`` adds parts
        of unknown correlation with it, which go with the map term.
    kind : ndarray of int, shape (N,)
        ``RANGE_BEARING``, ``RANGE`` or ``BEARING`` per row.
    settings : UpdateSettings
        Gates, correlation and iteration (``LocalizerConfig``); a caller that wants
        another correlation for some rows passes ``dataclasses.replace(settings,
        correlation=...)``.

    Returns
    -------
    UpdateResult

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to the pose.

    """
    z = np.where(np.isfinite(z), z, 0.0)
    noise = R if isinstance(R, SensorNoise) else SensorNoise(R, np.zeros_like(R))
    R_total = noise.R + noise.R_dep + (0.0 if noise.R_shared is None else noise.R_shared)
    d2, passed = _row_gate(x, P, m, P_m, z, R_total, kind, settings)
    used = passed.copy()
    if not used.any():
        return UpdateResult(x, P, used, ~passed, math.nan, 0, 1.0, 0)
    idx = np.flatnonzero(used)
    rows, comps = stacked_components(kind[idx])
    rows_g = idx[rows]
    _, _, J_z_m = observe(x, m[idx])
    M_rows = J_z_m @ P_m[idx] @ J_z_m.transpose(0, 2, 1)
    if settings.landmark_correlation == 'unknown':
        M_rows = landmark_bound(M_rows)
    M_rows = M_rows + noise.R_dep[idx]
    R_s, M_s = stacked_blocks(noise.R[idx], rows, comps), stacked_blocks(M_rows, rows, comps)
    if noise.R_shared is not None:  # one error in every row: the full block
        M_s = M_s + noise.R_shared[comps[:, None], comps[None, :]]
    z_s = z[rows_g, comps]
    h0, H0 = _stack(x, m, rows_g, comps)
    w = 1.0
    if settings.correlation == 'split_ci' and np.any(M_s):
        w = split_ci_weight(P, H0, R_s, M_s)
    P1, P2 = P / w, R_s + (M_s / (1.0 - w) if w < 1.0 else M_s)
    x_i, h_i, H_i, iterations = x, h0, H0, 0
    while True:
        S = H_i @ P1 @ H_i.T + P2
        K = np.linalg.solve(S, H_i @ P1).T
        nu = wrapped_innovation(z_s, h_i, comps) - H_i @ pose_difference(x, x_i)
        x_next = x + K @ nu
        x_next[2] = (x_next[2] + math.pi) % (2.0 * math.pi) - math.pi
        iterations += 1
        h_next, H_next = _stack(x_next, m, rows_g, comps)
        linear = h_i + H_i @ pose_difference(x_next, x_i)
        error = np.abs(wrapped_innovation(h_next, linear, comps))
        x_i, h_i, H_i_prev, H_i = x_next, h_next, H_i, H_next
        if (iterations >= settings.max_iterations
                or np.all(error <= settings.iterate_threshold * np.sqrt(np.diag(S)))):
            break
    K_f = np.linalg.solve(S, H_i_prev @ P1).T
    A = np.eye(len(x)) - K_f @ H_i_prev
    P_new = A @ P1 @ A.T + K_f @ P2 @ K_f.T
    S0 = H0 @ P @ H0.T + R_s + M_s
    nu0 = wrapped_innovation(z_s, h0, comps)
    nis = float(nu0 @ np.linalg.solve(S0, nu0))
    return UpdateResult(x_i, 0.5 * (P_new + P_new.T), used, ~passed, nis, len(rows), w,
                        iterations, A)


def pose_difference(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return ``a - b`` of two states (n,), the heading wrapped."""
    d = np.asarray(a, dtype=np.float64) - b
    d[2] = (d[2] + math.pi) % (2.0 * math.pi) - math.pi
    return d
