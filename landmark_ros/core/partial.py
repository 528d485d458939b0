"""
Partial observations: range-only (radio beacons, UWB) and bearing-only (camera) views.

A *view* is one scalar measurement of one landmark from a sensor whose world pose is
uncertain. One view does not fix a 2D point, so a landmark is first *initialised*
from several views once their geometry determines it (delayed initialisation, as in
bearing-only SLAM), then *updated* by an EKF one view at a time, with the fusion
methods of ``gaussian``: the plain update (``independent``), covariance
intersection and split covariance intersection.

Symbols
-------
kind : ``RANGE`` (0) or ``BEARING`` (1), shape () or (N,); the column of
    ``sensors.observe`` the view measures, so ``h`` is ``sensors.observe``'s.
s : sensor pose in the world ``(x, y, theta)``, shape (3,) or (N, 3).
P_s : its covariance, shape (3, 3) or (N, 3, 3): the robot pose covariance pushed
    through the mounting, first order (``views_from_robot``).
y : measured value, range [m] or bearing [rad], shape (N,).
R : variance of the independent sensor noise [m^2] or [rad^2], shape (N,).
R_bias : variance of a sensor bias shared by the sensor's views, shape (N,).
h : predicted value ``h(s, m)``, shape (1,) or (N, 1).
J_h_s, J_h_m : its Jacobians, shapes (1, 3) and (1, 2) or (N, 1, 3) and (N, 1, 2).
R_eff : effective variance of a view at ``m``, ``R + R_bias + J_h_s P_s J_h_s^T``
    (the pose uncertainty pushed into the measurement), shape (N,).
R_dep : its dependent part ``R_bias + J_h_s P_s J_h_s^T``: the pose term is shared by
    every view made from that pose, the bias by every view of that sensor, shape (N,).
m : landmark in the world, shape (2,) or (N, 2) [m].
P_m, P_m_dep : its covariance and the dependent part of it, shape (2, 2) or
    (N, 2, 2) [m^2]; the independent part is ``P_m - P_m_dep``.

A residual is ``y - h`` with bearings wrapped to [-pi, pi).

"""

from dataclasses import dataclass, fields
import math
from typing import Any, Iterable, List, Optional, Tuple, TYPE_CHECKING, Union

from landmark_ros.core import sensors
from landmark_ros.core.curvature import CONFIDENCE_RADIUS_95, observe_hessians, \
    relative_curvatures
from landmark_ros.core.gaussian import chi2_threshold
from landmark_ros.core.landmarks import sensor_in_world
from landmark_ros.core.pose2 import wrap_angle
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

RANGE = 0
"""Kind of a range view: column 0 of ``sensors.observe``."""

BEARING = 1
"""Kind of a bearing view: column 1 of ``sensors.observe``."""

KIND_NAMES = {RANGE: 'range', BEARING: 'bearing'}
"""Names of the view kinds, as parameters and messages spell them."""

OK = 'ok'
WAIT = 'wait'
WAIT_REASONS = (
    'too_few_views', 'rays_do_not_cross', 'small_crossing_angle', 'no_intersection',
    'no_convergence', 'ambiguous', 'ill_conditioned', 'too_uncertain', 'too_curved',
    'inconsistent')
"""Why ``initialise`` waits for more views, as counters and logs name it."""

UPDATED = 0
GATED = 1
TOO_CLOSE = 2
UPDATE_STATUS_NAMES = {UPDATED: 'updated', GATED: 'gated', TOO_CLOSE: 'too_close'}
"""Names of the codes ``update`` returns per row."""

METHODS = ('independent', 'covariance_intersection', 'split_covariance_intersection')
"""Fusion methods of ``update``, named as the fuser's ``fusion`` parameter names them."""

OMEGA_EDGE = 1e-9
"""The fusion weight is searched in ``[OMEGA_EDGE, 1 - OMEGA_EDGE]``."""

_OMEGA_STEPS = 60
"""Bisection steps on the weight: the bracket shrinks below 1e-18."""

_COLLINEAR = 1e-9
"""Centres whose smaller singular value is below this fraction of the larger are collinear."""


def _kinds(kind):
    array = np.asarray(kind)
    if array.dtype.kind in 'USO':
        names = {name: code for code, name in KIND_NAMES.items()}
        flat = [names.get(str(k)) for k in array.reshape(-1)]
        if None in flat:
            raise ValueError(f"kind must be 'range' or 'bearing', got {kind!r}")
        return np.array(flat, dtype=np.int64).reshape(array.shape)
    if array.dtype.kind not in 'iu' or not np.isin(array, (RANGE, BEARING)).all():
        raise ValueError(f'kind must be RANGE (0) or BEARING (1), got {kind!r}')
    return array.astype(np.int64)


@dataclass(frozen=True)
class Views:
    """
    A batch of ``N`` views: scalar measurements of landmarks from uncertain sensors.

    Every field is broadcast to the batch on construction (a single view is a batch
    of one), converted to float64 (``kind`` to int64) and checked. Bearings are
    wrapped to [-pi, pi).

    Attributes
    ----------
    kind : ndarray of int, shape (N,)
        ``RANGE`` or ``BEARING`` (or the names ``'range'``, ``'bearing'`` on input).
    s : ndarray, shape (N, 3)
        Sensor pose in the world (x [m], y [m], theta [rad]).
    P_s : ndarray, shape (N, 3, 3)
        Its covariance (treated as dependent: shared by the views from that pose).
    y : ndarray, shape (N,)
        Measured range [m] or bearing [rad].
    R : ndarray, shape (N,)
        Variance of the independent sensor noise [m^2] or [rad^2], positive.
    R_bias : ndarray, shape (N,)
        Variance of a sensor bias (dependent), non-negative; zero by default.

    Raises
    ------
    ValueError
        On a wrong shape or kind, a non-finite value, ``R <= 0``, ``R_bias < 0`` or a
        ``P_s`` that is not symmetric positive semi-definite.

    """

    kind: NDArray[np.int64]
    s: NDArray[np.float64]
    P_s: NDArray[np.float64]
    y: NDArray[np.float64]
    R: NDArray[np.float64]
    # Any array_like on input: __post_init__ makes every field an array (0.0 too).
    R_bias: NDArray[np.float64] = 0.0  # type: ignore[assignment]

    if TYPE_CHECKING:
        # The constructor takes array_like fields (what __post_init__ converts).
        def __init__(self, kind: ArrayLike, s: ArrayLike, P_s: ArrayLike, y: ArrayLike,
                     R: ArrayLike, R_bias: ArrayLike = 0.0) -> None:
            ...

    def __post_init__(self) -> None:
        """Broadcast, convert and check the fields."""
        kind = _kinds(self.kind)
        s = np.asarray(self.s, dtype=np.float64)
        P_s = np.asarray(self.P_s, dtype=np.float64)
        y, R, R_bias = (np.asarray(x, dtype=np.float64) for x in (self.y, self.R, self.R_bias))
        if s.ndim not in (1, 2) or s.shape[-1] != 3:
            raise ValueError(f's must have shape (3,) or (N, 3), got {s.shape}')
        if P_s.ndim not in (2, 3) or P_s.shape[-2:] != (3, 3):
            raise ValueError(f'P_s must have shape (3, 3) or (N, 3, 3), got {P_s.shape}')
        for name, x in (('kind', kind), ('y', y), ('R', R), ('R_bias', R_bias)):
            if x.ndim > 1:
                raise ValueError(f'{name} must have shape () or (N,), got {x.shape}')
        try:
            shape = np.broadcast_shapes(kind.shape, s.shape[:-1], P_s.shape[:-2], y.shape,
                                        R.shape, R_bias.shape)
        except ValueError as error:
            raise ValueError(f'views disagree on N: {error}') from None
        shape = shape or (1,)
        kind = np.broadcast_to(kind, shape).copy()
        s = np.broadcast_to(s, shape + (3,)).copy()
        s[:, 2] = wrap_angle(s[:, 2])
        P_s = np.broadcast_to(P_s, shape + (3, 3)).copy()
        y = np.broadcast_to(y, shape).copy()
        y = np.where(kind == BEARING, wrap_angle(y), y)
        R, R_bias = (np.broadcast_to(x, shape).copy() for x in (R, R_bias))
        for name, x in (('s', s), ('P_s', P_s), ('y', y), ('R', R), ('R_bias', R_bias)):
            if not np.all(np.isfinite(x)):
                raise ValueError(f'{name} must be finite')
        if not np.all(R > 0.0):
            raise ValueError(f'R must be positive, got {R}')
        if not np.all(R_bias >= 0.0):
            raise ValueError(f'R_bias must be non-negative, got {R_bias}')
        scale = np.maximum(np.abs(P_s).max(axis=(-2, -1)), 1e-300)
        if not np.all(np.abs(P_s - np.swapaxes(P_s, -1, -2)).max(axis=(-2, -1))
                      <= 1e-9 * scale):
            raise ValueError('P_s must be symmetric')
        if not np.all(np.linalg.eigvalsh(P_s)[:, 0] >= -1e-9 * scale):
            raise ValueError('P_s must be positive semi-definite')
        for name, value in (('kind', kind), ('s', s), ('P_s', P_s), ('y', y), ('R', R),
                            ('R_bias', R_bias)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        """Return the number of views ``N``."""
        return self.kind.shape[0]

    def __getitem__(self, index: Union[int, np.integer[Any], slice, NDArray[Any]]) -> 'Views':
        """Return the views selected by an index, a slice or a mask, as a batch."""
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        return Views(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @staticmethod
    def concatenate(batches: Iterable['Views']) -> 'Views':
        """Return one batch holding the views of several, in order."""
        batches = list(batches)
        return Views(**{f.name: np.concatenate([getattr(b, f.name) for b in batches])
                        for f in fields(Views)})


def views_from_robot(kind: ArrayLike, pose: ArrayLike, P_pose: ArrayLike, y: ArrayLike,
                     R: ArrayLike, R_bias: ArrayLike = 0.0,
                     sensor_pose: Optional[ArrayLike] = None) -> Views:
    """
    Make views from robot poses, their covariances and the sensor mounting.

    Source: the first-order composition of ``landmarks.sensor_in_world``
    (``P_s = J_s_pose P_pose J_s_pose^T``, the mounting exact).

    Parameters
    ----------
    kind : int, str or array_like, shape () or (N,)
        ``RANGE``, ``BEARING`` or their names.
    pose : array_like, shape (3,) or (N, 3)
        Robot pose (x, y, theta).
    P_pose : array_like, shape (3, 3) or (N, 3, 3)
        Covariance of the robot pose.
    y : array_like, shape () or (N,)
        Measured range [m] or bearing [rad].
    R : array_like, shape () or (N,)
        Variance of the independent sensor noise.
    R_bias : array_like, shape () or (N,)
        Variance of the sensor bias (dependent).
    sensor_pose : array_like, shape (3,) or (N, 3), optional
        Sensor pose in the robot frame; ``None`` means the robot origin.

    Returns
    -------
    Views

    Raises
    ------
    ValueError
        As ``Views`` does.

    """
    s, P_s = sensor_in_world(pose, P_pose, sensor_pose)
    return Views(kind, s, P_s, y, R, R_bias)


# --- the model: h, its Jacobians, residuals, effective variances --------------------------

def observe_view(kind: ArrayLike, s: ArrayLike, m: ArrayLike) -> NDArray[np.float64]:
    """
    Predict a scalar view: the ``kind`` column of ``sensors.observe(s, m)``.

    Source: the chapter's range-bearing model ``sensors.observe``; a range view is
    ``|m - s_xy|``, a bearing view ``wrap(atan2(dy, dx) - theta)``.

    Parameters
    ----------
    kind : int or array_like of int, shape () or (N,)
        ``RANGE`` or ``BEARING``.
    s : array_like, shape (3,) or (N, 3)
        Sensor pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    h : ndarray, shape (1,) or (N, 1)
        Range [m] or bearing [rad].

    Raises
    ------
    ValueError
        If the landmark is closer than ``sensors.MIN_RANGE`` to the sensor.

    """
    kind = _kinds(kind)
    z = sensors.observe(s, m)
    shape = np.broadcast_shapes(kind.shape, z.shape[:-1])
    z = np.broadcast_to(z, shape + (2,))
    return np.take_along_axis(z, np.broadcast_to(kind, shape)[..., None], axis=-1)


def observe_view_jacobians(kind: ArrayLike, s: ArrayLike,
                           m: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``observe_view``: rows of ``sensors.observe_jacobians``.

    Parameters
    ----------
    kind : int or array_like of int, shape () or (N,)
        ``RANGE`` or ``BEARING``.
    s : array_like, shape (3,) or (N, 3)
        Sensor pose (x, y, theta).
    m : array_like, shape (2,) or (N, 2) [m]
        Landmark position in the world.

    Returns
    -------
    J_h_s : ndarray, shape (1, 3) or (N, 1, 3)
    J_h_m : ndarray, shape (1, 2) or (N, 1, 2)

    Raises
    ------
    ValueError
        If the landmark is closer than ``sensors.MIN_RANGE`` to the sensor.

    """
    kind = _kinds(kind)
    J_z_s, J_z_m = sensors.observe_jacobians(s, m)
    shape = np.broadcast_shapes(kind.shape, J_z_s.shape[:-2])
    row = np.broadcast_to(kind, shape)[..., None, None]
    J_h_s = np.take_along_axis(np.broadcast_to(J_z_s, shape + (2, 3)), row, axis=-2)
    J_h_m = np.take_along_axis(np.broadcast_to(J_z_m, shape + (2, 2)), row, axis=-2)
    return J_h_s, J_h_m


@dataclass(frozen=True)
class Linearisation:
    """
    The views linearised at landmark positions.

    Attributes
    ----------
    residual : ndarray, shape (N,)
        ``y - h(s, m)``, bearings wrapped to [-pi, pi).
    J_h_s : ndarray, shape (N, 1, 3)
    J_h_m : ndarray, shape (N, 1, 2)
    R_eff : ndarray, shape (N,)
        ``R + R_bias + J_h_s P_s J_h_s^T``.
    R_dep : ndarray, shape (N,)
        ``R_bias + J_h_s P_s J_h_s^T``.

    """

    residual: NDArray[np.float64]
    J_h_s: NDArray[np.float64]
    J_h_m: NDArray[np.float64]
    R_eff: NDArray[np.float64]
    R_dep: NDArray[np.float64]


def linearise(views: Views, m: ArrayLike) -> Linearisation:
    """
    Return residuals, Jacobians and effective variances of views at a landmark.

    Source: first-order propagation of the sensor pose error into the measurement,
    ``R_eff = R + J_h_s P_s J_h_s^T`` (Bar-Shalom, Li, Kirubarajan, *Estimation with
    Applications to Tracking and Navigation*, 2001, sec. 10.3, "Jacobian" of a
    nonlinear measurement with uncertain parameters).

    Parameters
    ----------
    views : Views
        ``N`` views.
    m : array_like, shape (2,) or (N, 2) [m]
        One landmark for all views or one per view.

    Returns
    -------
    Linearisation

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to its sensor.

    """
    m = np.asarray(m, dtype=np.float64)
    h = observe_view(views.kind, views.s, m)[:, 0]
    residual = views.y - h
    residual = np.where(views.kind == BEARING, wrap_angle(residual), residual)
    J_h_s, J_h_m = observe_view_jacobians(views.kind, views.s, m)
    pose_term = np.einsum('ni,nij,nj->n', J_h_s[:, 0], views.P_s, J_h_s[:, 0])
    R_dep = views.R_bias + np.maximum(pose_term, 0.0)
    return Linearisation(residual, J_h_s, J_h_m, views.R + R_dep, R_dep)


def residuals(views: Views, m: ArrayLike) -> NDArray[np.float64]:
    """
    Return the residuals ``y - h(s, m)`` of views, bearings wrapped to [-pi, pi).

    Parameters
    ----------
    views : Views
        ``N`` views.
    m : array_like, shape (2,) or (N, 2) [m]
        One landmark for all views or one per view.

    Returns
    -------
    ndarray, shape (N,)

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to its sensor.

    """
    h = observe_view(views.kind, views.s, m)[:, 0]
    residual = views.y - h
    return np.where(views.kind == BEARING, wrap_angle(residual), residual)


def effective_variances(views: Views,
                        m: ArrayLike) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the effective variance of each view at a landmark and its dependent part.

    Parameters
    ----------
    views : Views
        ``N`` views.
    m : array_like, shape (2,) or (N, 2) [m]
        One landmark for all views or one per view.

    Returns
    -------
    R_eff : ndarray, shape (N,)
        ``R + R_bias + J_h_s P_s J_h_s^T`` [m^2] or [rad^2].
    R_dep : ndarray, shape (N,)
        ``R_bias + J_h_s P_s J_h_s^T``.

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to its sensor.

    """
    lin = linearise(views, m)
    return lin.R_eff, lin.R_dep


# --- closed-form geometry ------------------------------------------------------------------

def intersect_rays(
        s1: ArrayLike, phi1: ArrayLike, s2: ArrayLike, phi2: ArrayLike
) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """
    Intersect pairs of rays ``s1 + t1 d(phi1)`` and ``s2 + t2 d(phi2)``.

    Source: the 2D line intersection by cross products (Goldman, "Intersection of two
    lines in three-space", *Graphics Gems*, 1990, specialised to the plane).

    Parameters
    ----------
    s1, s2 : array_like, shape (2,) or (N, 2) [m]
        Ray origins (the sensor positions).
    phi1, phi2 : array_like, shape () or (N,) [rad]
        Ray directions in the world (sensor heading plus bearing).

    Returns
    -------
    point : ndarray, shape (2,) or (N, 2) [m]
        Intersection of the two lines; ``inf`` or NaN for parallel rays.
    t1, t2 : ndarray, shape () or (N,) [m]
        Distances along each ray; the rays cross in front of both where both are
        positive.
    crossing_angle : ndarray, shape () or (N,) [rad]
        Angle between the two lines in [0, pi/2]: 0 for parallel (or opposite) rays,
        where the intersection is undetermined.

    """
    s1, s2 = np.asarray(s1, dtype=np.float64), np.asarray(s2, dtype=np.float64)
    d1 = np.stack([np.cos(phi1), np.sin(phi1)], axis=-1)
    d2 = np.stack([np.cos(phi2), np.sin(phi2)], axis=-1)
    delta = s2 - s1
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        t1 = (delta[..., 0] * d2[..., 1] - delta[..., 1] * d2[..., 0]) / cross
        t2 = (delta[..., 0] * d1[..., 1] - delta[..., 1] * d1[..., 0]) / cross
    angle = np.abs(wrap_angle(np.asarray(phi2) - np.asarray(phi1)))
    crossing = np.minimum(angle, np.pi - angle)
    return s1 + t1[..., None] * d1, t1, t2, crossing


def intersect_circles(
        c1: ArrayLike, r1: ArrayLike, c2: ArrayLike, r2: ArrayLike
) -> Tuple[NDArray[np.float64], Union[np.bool_, NDArray[np.bool_]]]:
    """
    Intersect pairs of circles.

    Source: Bourke, "Intersection of two circles", 1997 (the radical line).

    Parameters
    ----------
    c1, c2 : array_like, shape (2,) or (N, 2) [m]
        Centres, at least ``sensors.MIN_RANGE`` apart.
    r1, r2 : array_like, shape () or (N,) [m]
        Radii.

    Returns
    -------
    points : ndarray, shape (2, 2) or (N, 2, 2) [m]
        The two intersections, left then right of the line from ``c1`` to ``c2``.
        Where the circles do not meet (noisy ranges) both are the point of the centre
        line closest to both circles.
    meet : ndarray of bool, shape () or (N,)
        Whether the circles meet.

    Raises
    ------
    ValueError
        If two centres are closer than ``sensors.MIN_RANGE``.

    """
    c1, c2 = np.asarray(c1, dtype=np.float64), np.asarray(c2, dtype=np.float64)
    r1, r2 = np.asarray(r1, dtype=np.float64), np.asarray(r2, dtype=np.float64)
    delta = c2 - c1
    d = np.hypot(delta[..., 0], delta[..., 1])
    sensors.check_range(d, 'distance between circle centres')
    u = delta / d[..., None]
    a = (r1 * r1 - r2 * r2 + d * d) / (2.0 * d)
    h2 = r1 * r1 - a * a
    meet = h2 >= 0.0
    h = np.sqrt(np.maximum(h2, 0.0))
    base = c1 + a[..., None] * u
    left = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    points = np.stack([base + h[..., None] * left, base - h[..., None] * left], axis=-2)
    return points, meet[()]


def intersect_ray_circle(
        s: ArrayLike, phi: ArrayLike, c: ArrayLike, r: ArrayLike
) -> Tuple[NDArray[np.float64], NDArray[np.float64], Union[np.bool_, NDArray[np.bool_]]]:
    """
    Intersect rays ``s + t d(phi)`` with circles.

    Source: the quadratic ``|s + t d - c|^2 = r^2`` in ``t``.

    Parameters
    ----------
    s : array_like, shape (2,) or (N, 2) [m]
        Ray origins.
    phi : array_like, shape () or (N,) [rad]
        Ray directions in the world.
    c : array_like, shape (2,) or (N, 2) [m]
        Circle centres.
    r : array_like, shape () or (N,) [m]
        Radii.

    Returns
    -------
    points : ndarray, shape (2, 2) or (N, 2, 2) [m]
        The two intersections of the line, nearer first; where they do not meet, both
        are the point of the line closest to the centre.
    t : ndarray, shape (2,) or (N, 2) [m]
        Their distances along the ray (negative: behind the sensor).
    meet : ndarray of bool, shape () or (N,)

    """
    s, c = np.asarray(s, dtype=np.float64), np.asarray(c, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    d = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    e = s - c
    b = np.sum(d * e, axis=-1)
    disc = b * b - (np.sum(e * e, axis=-1) - r * r)
    meet = disc >= 0.0
    root = np.sqrt(np.maximum(disc, 0.0))
    t = np.stack([-b - root, -b + root], axis=-1)
    return s[..., None, :] + t[..., None] * d[..., None, :], t, meet[()]


def trilaterate(c: ArrayLike, r: ArrayLike) -> Tuple[NDArray[np.float64], float]:
    """
    Place a point from ranges to three or more centres, linearised (no iteration).

    Subtracting the mean of the equations ``|m - c_i|^2 = r_i^2`` cancels ``|m|^2`` and
    leaves the linear system ``2 (c_i - c_mean) . m = ...``, solved by least squares.
    Source: Murphy and Hereman, "Determination of a position in three dimensions
    using trilateration and approximate distances", Colorado School of Mines report
    MCS-95-07, 1995 (here in the plane, centred for conditioning).

    Parameters
    ----------
    c : array_like, shape (N, 2) [m]
        Centres, ``N >= 3``.
    r : array_like, shape (N,) [m]
        Ranges.

    Returns
    -------
    m : ndarray, shape (2,) [m]
        The point; NaN where the centres are collinear (the mirror image of the point
        across their line fits as well).
    spread : float
        Smaller over larger singular value of the centred centres, in [0, 1]: 0 for
        collinear centres.

    Raises
    ------
    ValueError
        If there are fewer than three centres.

    """
    c = np.asarray(c, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] < 3 or c.shape[1] != 2 or r.shape != c.shape[:1]:
        raise ValueError(f'need (N, 2) centres and (N,) ranges with N >= 3, got {c.shape}, '
                         f'{r.shape}')
    mean = c.mean(axis=0)
    c = c - mean
    singular = np.linalg.svd(c, compute_uv=False)
    spread = float(singular[1] / singular[0]) if singular[0] > 0.0 else 0.0
    if spread < _COLLINEAR:
        return np.full(2, np.nan), spread
    q = np.sum(c * c, axis=1) - r * r
    m = np.linalg.lstsq(2.0 * c, q - q.mean(), rcond=None)[0]
    return m + mean, spread


# --- delayed initialisation ---------------------------------------------------------------

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
        return -observe_view_jacobians(views.kind, views.s, m)[1][:, 0, :] * w[:, None]

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


# --- EKF updates ---------------------------------------------------------------------------

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

    """

    m: NDArray[np.float64]
    P_m: NDArray[np.float64]
    P_m_dep: NDArray[np.float64]
    innovation: NDArray[np.float64]
    S: NDArray[np.float64]
    mahalanobis_sq: NDArray[np.float64]
    omega: NDArray[np.float64]
    status: NDArray[np.int64]

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
    one root: found by bisection in ``[OMEGA_EDGE, 1 - OMEGA_EDGE]``, vectorised.
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
            sub = tuple(x[inside] for x in args)
            a, b = lo[inside], hi[inside]
            for _ in range(_OMEGA_STEPS):
                mid = 0.5 * (a + b)
                rising = _posterior_log_det_slope(mid, *sub) > 0.0
                b = np.where(rising, mid, b)
                a = np.where(rising, a, mid)
            omega[inside] = 0.5 * (a + b)
    return omega


def update(m: ArrayLike, P_m: ArrayLike, views: Views, P_m_dep: Optional[ArrayLike] = None,
           method: str = 'independent', gate_probability: float = 0.999,
           omega: Optional[ArrayLike] = None) -> UpdateResult:
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

    omega minimises ``det P+`` (``view_omega``) unless given. Rows are independent
    pairs: a landmark seen by several views is updated by calling again (or by a loop
    over its views), not twice in one batch.

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
    if method == 'independent':
        omega = np.full(n, np.nan)
        A_dep, a_dep = P_dep, lin.R_dep
    else:
        if omega is None:
            if method == 'covariance_intersection':
                omega = view_omega(H, np.zeros_like(P_m), P_m, np.zeros(n), lin.R_eff)
            else:
                omega = view_omega(H, P_ind, P_dep, R_ind, lin.R_dep)
        omega = np.broadcast_to(np.asarray(omega, dtype=np.float64), (n,)).copy()
        if not np.all((omega > 0.0) & (omega < 1.0)):
            raise ValueError(f'omega must lie strictly between 0 and 1, got {omega}')
        w = omega[:, None, None]
        if method == 'covariance_intersection':
            A_dep = P_m / w - P_ind
            a_dep = lin.R_eff / (1.0 - omega) - R_ind
        else:
            A_dep = P_dep / w
            a_dep = lin.R_dep / (1.0 - omega)
    A = P_ind + A_dep
    K = (A @ H[:, :, None])[:, :, 0] / (_quadratic(H, A) + R_ind + a_dep)[:, None]
    L = np.eye(2) - K[:, :, None] * H[:, None, :]
    KK = K[:, :, None] * K[:, None, :]
    new_ind = L @ P_ind @ np.swapaxes(L, -1, -2) + KK * R_ind[:, None, None]
    new_dep = L @ A_dep @ np.swapaxes(L, -1, -2) + KK * a_dep[:, None, None]
    new_ind = 0.5 * (new_ind + np.swapaxes(new_ind, -1, -2))
    new_dep = 0.5 * (new_dep + np.swapaxes(new_dep, -1, -2))
    keep = status == UPDATED
    m_new = np.where(keep[:, None], m + K * np.where(keep, innovation, 0.0)[:, None], m)
    P_new = np.where(keep[:, None, None], new_ind + new_dep, P_m)
    dep_new = np.where(keep[:, None, None], new_dep, P_dep)
    return UpdateResult(m_new, P_new, dep_new, innovation, S, d2, omega, status)
