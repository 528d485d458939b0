"""
Delayed initialisation of a landmark from views (``partial.initialise``).

The views' geometry (are they enough, and far enough apart?), the closed-form first
guesses, the weighted least squares refinement from each (``scipy.optimize``), the
choice among distinct solutions, the dependent covariance, and the linearity rule
(Bates and Watts' relative curvature) that makes a landmark wait. Private to
``core``: ``partial`` is the interface.
"""

from dataclasses import dataclass
import math
from typing import List, Optional

from landmark_ros.core import sensors
from landmark_ros.core._partial_geometry import (intersect_circles, intersect_ray_circle,
                                                 intersect_rays, trilaterate)
from landmark_ros.core._partial_model import (BEARING, Linearisation, linearise,
                                              observe_views_jacobians, OK, RANGE, residuals,
                                              Views, WAIT)
from landmark_ros.core.curvature import CONFIDENCE_RADIUS_95, observe_hessians, \
    relative_curvatures
from landmark_ros.core.gating import chi2_threshold
import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class InitialiseParams:
    """
    Parameters of ``initialise``, checked on construction.

    Attributes
    ----------
    min_triangulation_angle_deg : float
        Bearing-only landmarks wait until two rays cross in front of both sensors at
        least at this angle [deg], in (0, 90).
    max_condition : float
        Largest condition number of the information ``J^T W J``; beyond, wait.
    max_stddev : float
        Largest standard deviation [m] of the position (along its worst direction).
    max_relative_stddev : float
        Largest standard deviation of the position (worst direction) over its distance
        to the nearest sensor of its views: the EKF updates that follow linearise
        ``h`` at the estimate, which holds only while the uncertainty is small
        against the range (the linearity condition of delayed initialisation,
        Bailey, ICRA 2003). Beyond, wait (``too_uncertain``).
    max_curvature_ratio : float or None
        Largest ratio of the radius of the 95 % confidence region (2.45 standard
        deviations) to the radius of curvature of the fit, parameter effects or
        intrinsic (``curvature.relative_curvatures``): beyond, the Gaussian
        ``P_m`` does not describe the error (a curved valley of ranges from a short
        stretch of path) and the landmark waits (``too_curved``). 0.5 is Bates and
        Watts' rule (1980); ``None`` skips.
    ambiguity_chi2 : float
        A second local minimum whose cost (sum of squared normalised residuals) is
        within this of the best makes the landmark ambiguous (two circles: two points).
        The default is the 99.9 % point of chi-square with 1 dof. A second minimum
        that passes the ``consistency_probability`` test is ambiguous too.
    consistency_probability : float or None
        With more views than unknowns, wait (``inconsistent``) when the cost exceeds
        the chi-square quantile with ``N - 2`` dof at this probability; ``None`` skips.
    loss : str
        ``scipy.optimize.least_squares`` loss: ``'linear'`` (plain least squares),
        ``'huber'``, ``'soft_l1'``, ``'cauchy'`` or ``'arctan'``.
    f_scale : float
        Normalised residual at which a robust loss starts to down-weight (in sigmas).

    Raises
    ------
    ValueError
        If a value is out of range.

    """

    min_triangulation_angle_deg: float = 5.0
    max_condition: float = 1e6
    max_stddev: float = 10.0
    max_relative_stddev: float = 0.1
    max_curvature_ratio: Optional[float] = 0.5
    ambiguity_chi2: float = 10.827566170662733
    consistency_probability: Optional[float] = 0.999
    loss: str = 'linear'
    f_scale: float = 1.0

    def __post_init__(self) -> None:
        """Check every value."""
        if not 0.0 < self.min_triangulation_angle_deg < 90.0:
            raise ValueError('min_triangulation_angle_deg must lie in (0, 90), got '
                             f'{self.min_triangulation_angle_deg!r}')
        if not self.max_condition >= 1.0:
            raise ValueError(f'max_condition must be >= 1, got {self.max_condition!r}')
        for name in ('max_stddev', 'max_relative_stddev', 'ambiguity_chi2', 'f_scale'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be positive, got {getattr(self, name)!r}')
        if self.max_curvature_ratio is not None and not self.max_curvature_ratio > 0.0:
            raise ValueError('max_curvature_ratio must be positive or None, got '
                             f'{self.max_curvature_ratio!r}')
        p = self.consistency_probability
        if p is not None and not 0.0 < p < 1.0:
            raise ValueError(f'consistency_probability must lie in (0, 1) or be None, got {p!r}')
        if self.loss not in ('linear', 'huber', 'soft_l1', 'cauchy', 'arctan'):
            raise ValueError(f'unknown loss {self.loss!r}')


@dataclass(frozen=True)
class Geometry:
    """
    What the closed forms make of a landmark's views, before any optimisation.

    Attributes
    ----------
    reason : str
        ``'ok'`` or why the views cannot place the landmark yet (``WAIT_REASONS``).
    candidates : ndarray, shape (K, 2) [m]
        Starting points: the best ray intersection, trilateration, both intersections
        of two circles, both ray-circle intersections in front of the sensor.
    crossing_angle : float [rad]
        Largest crossing angle of two bearing rays that meet in front of both
        sensors; NaN with fewer than two bearings or none meeting in front.

    """

    reason: str
    candidates: NDArray[np.float64]
    crossing_angle: float


def geometry(views: Views, params: InitialiseParams = InitialiseParams()) -> Geometry:
    """
    Check whether views can place a landmark and return closed-form starting points.

    Bearing-only landmarks need two rays that cross in front of both sensors at no
    less than ``min_triangulation_angle_deg`` (delayed initialisation: Bailey,
    "Constrained initialisation for bearing-only SLAM", ICRA 2003). Ranges give the
    linearised trilateration of non-collinear centres, and always both intersections
    of the two circles with the farthest centres; a bearing and a range give both
    ray-circle intersections in front of the camera. Ambiguities (the mirror point of
    two circles) are settled by ``initialise``, which refines every candidate.

    Parameters
    ----------
    views : Views
        The views of one landmark.
    params : InitialiseParams
        Thresholds.

    Returns
    -------
    Geometry

    """
    n = len(views)
    if n < 2:
        return Geometry('too_few_views', np.empty((0, 2)), math.nan)
    xy, phi = views.s[:, :2], views.s[:, 2] + views.y
    bearings = np.flatnonzero(views.kind == BEARING)
    ranges = np.flatnonzero(views.kind == RANGE)
    candidates = []
    crossing = math.nan
    bearing_reason = None
    if bearings.size >= 2:
        i, j = np.triu_indices(bearings.size, 1)
        i, j = bearings[i], bearings[j]
        point, t1, t2, angle = intersect_rays(xy[i], phi[i], xy[j], phi[j])
        front = (t1 > sensors.MIN_RANGE) & (t2 > sensors.MIN_RANGE) & np.isfinite(
            point).all(axis=1)
        if front.any():
            best = int(np.argmax(np.where(front, angle, -1.0)))
            crossing = float(angle[best])
            if crossing >= math.radians(params.min_triangulation_angle_deg):
                candidates.append(point[best])
            else:
                bearing_reason = 'small_crossing_angle'
        else:
            bearing_reason = 'rays_do_not_cross'
    if ranges.size >= 3:
        point, _ = trilaterate(xy[ranges], views.y[ranges])
        if np.isfinite(point).all():
            candidates.append(point)
    if ranges.size >= 2:
        i, j = np.triu_indices(ranges.size, 1)
        i, j = ranges[i], ranges[j]
        distance = np.hypot(*(xy[j] - xy[i]).T)
        best = int(np.argmax(distance))
        if distance[best] >= sensors.MIN_RANGE:
            points, _ = intersect_circles(xy[i[best]], views.y[i[best]], xy[j[best]],
                                          views.y[j[best]])
            candidates.extend(points)
    if bearings.size and ranges.size:
        # A few pairs are enough to start from; the optimisation uses every view.
        i, j = np.meshgrid(bearings[:3], ranges[:3], indexing='ij')
        i, j = i.reshape(-1), j.reshape(-1)
        points, t, _ = intersect_ray_circle(xy[i], phi[i], xy[j], views.y[j])
        candidates.extend(points[t > sensors.MIN_RANGE])
    if not ranges.size and bearing_reason:
        return Geometry(bearing_reason, np.empty((0, 2)), crossing)
    if not candidates:
        return Geometry(bearing_reason or 'no_intersection', np.empty((0, 2)), crossing)
    return Geometry(OK, np.array(candidates), crossing)


@dataclass(frozen=True)
class Initialisation:
    """
    The result of ``initialise``: a landmark, or why it must wait for more views.

    Attributes
    ----------
    status : str
        ``'ok'`` or ``'wait'``.
    reason : str
        ``'ok'`` or one of ``WAIT_REASONS``.
    m : ndarray, shape (2,) [m]
        The landmark; NaN while waiting.
    P_m : ndarray, shape (2, 2) [m^2]
        Its covariance ``(J^T W J)^-1``, ``W = diag(1 / R_eff)``; NaN while waiting.
    P_m_dep : ndarray, shape (2, 2) [m^2]
        The part of ``P_m`` due to the views' dependent parts; NaN while waiting.
    cost : float
        Sum of squared normalised residuals at the solution (chi-square with ``dof``
        degrees of freedom when consistent); NaN if nothing converged.
    dof : int
        Views minus 2.
    condition : float
        Condition number of the information at the solution; NaN if none.
    crossing_angle : float [rad]
        From ``Geometry``.
    n_views : int

    """

    status: str
    reason: str
    m: NDArray[np.float64]
    P_m: NDArray[np.float64]
    P_m_dep: NDArray[np.float64]
    cost: float
    dof: int
    condition: float
    crossing_angle: float
    n_views: int

    @property
    def ok(self) -> bool:
        """Return whether the landmark was placed."""
        return self.status == OK


@dataclass(frozen=True)
class _Solution:
    m: np.ndarray
    cost: float
    information: np.ndarray
    lin: Linearisation


def _refine(views, m0, params, reweight):
    """
    Weighted nonlinear least squares from ``m0``, weights ``1 / R_eff`` at ``m0``.

    With ``reweight`` the weights are evaluated again at the solution and the fit
    repeated from there (tighter tolerances); ``None`` if a step lands on a sensor.
    """
    def fun(m, w):
        return residuals(views, m) * w

    def jac(m, w):
        return -observe_views_jacobians(views, m)[1][:, 0, :] * w[:, None]

    from scipy.optimize import least_squares  # a second or more: when first needed
    m = np.asarray(m0, dtype=np.float64)
    try:
        for tol in ((1e-10, 1e-14) if reweight else (1e-10,)):
            w = 1.0 / np.sqrt(linearise(views, m).R_eff)
            fit = least_squares(fun, m, jac, args=(w,), method='trf', loss=params.loss,
                                f_scale=params.f_scale, x_scale='jac', xtol=tol, ftol=tol,
                                gtol=tol, max_nfev=200)
            m = fit.x
        lin = linearise(views, m)
    except ValueError:  # a step landed on a sensor
        return None
    if not np.isfinite(m).all():
        return None
    J = lin.J_h_m[:, 0, :]
    information = J.T @ (J / lin.R_eff[:, None])
    cost = float(np.sum(lin.residual ** 2 / lin.R_eff))
    return _Solution(m, cost, 0.5 * (information + information.T), lin)


def _distinct(solutions):
    """Keep the first of solutions closer than 1e-3 sigma to each other (sorted by cost)."""
    kept: List[_Solution] = []
    for solution in sorted(solutions, key=lambda s: s.cost):
        if all((d := solution.m - k.m) @ k.information @ d > 1e-6 for k in kept):
            kept.append(solution)
    return kept


def dependent_covariance(views: Views, lin: Linearisation,
                         bias_group: Optional[ArrayLike] = None,
                         pose_group: Optional[ArrayLike] = None) -> NDArray[np.float64]:
    """
    Return the covariance of the dependent errors of views, with their cross terms.

    The diagonal is ``R_dep`` (bias and pose term). Two views of one kind in one
    ``bias_group`` share the sensor bias (covariance ``sqrt(R_bias_i R_bias_j)``); two
    views in one ``pose_group`` share the sensor pose error (``J_h_s,i P_s J_h_s,j^T``).

    Parameters
    ----------
    views : Views
        ``N`` views.
    lin : Linearisation
        The views linearised at the landmark.
    bias_group, pose_group : array_like of int, shape (N,), optional
        Equal numbers for views sharing the bias (one sensor) or the pose error (one
        pose of one robot); None: no view shares it with another.

    Returns
    -------
    ndarray, shape (N, N)

    """
    n = len(views)
    D = np.diag(lin.R_dep)
    if bias_group is not None:
        b = np.asarray(bias_group)
        same = (b[:, None] == b[None, :]) & (views.kind[:, None] == views.kind[None, :])
        D = D + np.where(same & ~np.eye(n, dtype=bool),
                         np.sqrt(np.outer(views.R_bias, views.R_bias)), 0.0)
    if pose_group is not None:
        g = np.asarray(pose_group)
        same = (g[:, None] == g[None, :]) & ~np.eye(n, dtype=bool)
        if same.any():
            J = lin.J_h_s[:, 0, :]
            cross = np.einsum('ik,ikl,jl->ij', J, views.P_s, J)
            D = D + np.where(same, 0.5 * (cross + cross.T), 0.0)
    return D


def initialise(views: Views, params: InitialiseParams = InitialiseParams(),
               bias_group: Optional[ArrayLike] = None,
               pose_group: Optional[ArrayLike] = None) -> Initialisation:
    """
    Place a landmark from its views, or say why it must wait for more.

    Every closed-form candidate of ``geometry`` is refined by weighted nonlinear
    least squares (``scipy.optimize.least_squares``, trust-region reflective,
    weights ``1 / R_eff`` at the candidate; a robust ``loss`` changes the point, not
    the covariance); each distinct minimum is then fitted again with the weights
    evaluated there. The best solution
    wins unless a distinct one (Mahalanobis distance above 1 under the best's
    covariance) has a cost within ``ambiguity_chi2`` of it or itself passes the
    goodness-of-fit test of ``consistency_probability``: the data cannot reject it
    (two circles meet twice; ranges from a nearly straight path fit the mirror image
    of the landmark almost as well, and which one fits best is then down to the
    noise). The
    covariance is the inverse of the information of the normal equations,
    ``P_m = (J^T W J)^-1`` (Hartley and Zisserman, *Multiple View Geometry*, 2nd ed.,
    2003, sec. 5.2.3), and its dependent part
    ``P_m_dep = P_m J^T W diag(R_dep) W J P_m`` (the same linear map applied to the
    dependent part of each view's error). Views are treated as independent of each
    other: pose errors of different views must be uncorrelated for ``P_m`` to be
    consistent (the dependent part says how much of it a later split CI must treat
    as correlated with other estimates). With ``bias_group`` and ``pose_group`` the
    covariance is the sandwich ``B (R + D) B^T`` with ``B = P_m J^T W`` and ``D`` the
    dependent covariance with its cross terms (``dependent_covariance``), and
    ``P_m_dep = B D B^T``: views of one sensor share its bias, views of one pose its
    error, and these do not average out.

    Parameters
    ----------
    views : Views
        The views of one landmark (kinds may mix).
    params : InitialiseParams
        Thresholds, loss.
    bias_group, pose_group : array_like of int, shape (N,), optional
        Which views share a sensor bias and which a pose error
        (``dependent_covariance``): their cross-covariances enter ``P_m`` and
        ``P_m_dep`` (the least-squares weights stay diagonal). None: independent.

    Returns
    -------
    Initialisation
        ``status`` ``'wait'`` with a ``reason`` when the geometry does not determine
        the landmark: too few views, rays that do not cross or cross at too small an
        angle, an ambiguous or ill-conditioned solution, a too uncertain or too
        curved one (``max_curvature_ratio``), or
        residuals inconsistent with the declared variances.

    """
    n = len(views)
    geo = geometry(views, params)

    def wait(reason, solution=None, condition=math.nan):
        nan2, nan22 = np.full(2, np.nan), np.full((2, 2), np.nan)
        cost = solution.cost if solution is not None else math.nan
        return Initialisation(WAIT, reason, nan2, nan22, nan22, cost, n - 2, condition,
                              geo.crossing_angle, n)

    if geo.reason != OK:
        return wait(geo.reason)
    # A coarse fit from every candidate, then the distinct minima refined again.
    solutions = _distinct(s for s in (_refine(views, m0, params, False)
                                      for m0 in geo.candidates) if s is not None)
    solutions = [s for s in (_refine(views, s.m, params, True) for s in solutions)
                 if s is not None]
    if not solutions:
        return wait('no_convergence')
    solutions.sort(key=lambda s: s.cost)
    best = solutions[0]
    eigenvalues = np.linalg.eigvalsh(best.information)
    condition = eigenvalues[1] / eigenvalues[0] if eigenvalues[0] > 0.0 else math.inf
    # A distinct minimum the data cannot reject: its cost is close to the best's, or
    # it passes the goodness-of-fit test itself.
    plausible = params.ambiguity_chi2
    if params.consistency_probability is not None and n > 2:
        plausible = max(plausible, chi2_threshold(n - 2, params.consistency_probability)
                        - best.cost)
    for other in solutions[1:]:
        d = other.m - best.m
        if d @ best.information @ d > 1.0 and other.cost - best.cost < plausible:
            return wait('ambiguous', best, condition)
    if not condition <= params.max_condition:
        return wait('ill_conditioned', best, condition)
    nearest = float(np.min(np.hypot(*(views.s[:, :2] - best.m).T)))
    if not 1.0 / eigenvalues[0] <= min(params.max_stddev,
                                       params.max_relative_stddev * nearest) ** 2:
        return wait('too_uncertain', best, condition)
    if params.max_curvature_ratio is not None:
        H_h_m = observe_hessians(views.s, best.m)[np.arange(n), views.kind]
        curvature = max(relative_curvatures(best.lin.J_h_m[:, 0, :], H_h_m, best.lin.R_eff))
        if not curvature * CONFIDENCE_RADIUS_95 <= params.max_curvature_ratio:
            return wait('too_curved', best, condition)
    if (params.consistency_probability is not None and n > 2
            and best.cost > chi2_threshold(n - 2, params.consistency_probability)):
        return wait('inconsistent', best, condition)
    P_m = np.linalg.solve(best.information, np.eye(2))
    P_m = 0.5 * (P_m + P_m.T)
    lin = best.lin
    J = lin.J_h_m[:, 0, :]
    B = P_m @ (J.T / lin.R_eff)                  # (2, N): d m / d y
    P_m_dep = (B * lin.R_dep) @ B.T
    if bias_group is not None or pose_group is not None:
        # The sandwich B (R + D) B^T: the weights ignore the cross terms, the
        # covariance of what they produce does not.
        P_m_dep = B @ dependent_covariance(views, lin, bias_group, pose_group) @ B.T
        P_m = (B * views.R) @ B.T + P_m_dep
    return Initialisation(OK, OK, best.m, P_m, 0.5 * (P_m_dep + P_m_dep.T), best.cost, n - 2,
                          float(condition), geo.crossing_angle, n)
