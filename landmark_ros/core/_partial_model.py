"""
The views of ``partial`` and their model: kinds, ``Views``, ``h`` and its Jacobians.

The constants, ``Views`` and ``views_from_robot``, the measurement model of a view
(``observe_view``, its Jacobians), the linearisation at a landmark estimate,
residuals and effective variances. Private to ``core``: ``partial`` is the interface
and its module docstring names the symbols.

Source: the range and bearing models of the textbook chapter (``sensors``); the
pose term pushed through the Jacobian to first order.
"""

from dataclasses import dataclass, fields
from typing import Any, Dict, Iterable, Optional, Tuple, TYPE_CHECKING, Union

from landmark_ros.core import sensors
from landmark_ros.core.landmarks import sensor_in_world
from landmark_ros.core.pose2 import wrap_angle
from landmark_ros.core.range_scale import MIN_SCALE
import numpy as np
from numpy.typing import ArrayLike, NDArray


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

NO_RANGE_SCALE = (0.0, 0.0, 0.0)
"""``Views.range_scale`` of a sensor whose range has no bearing-dependent scale."""

METHODS = ('independent', 'covariance_intersection', 'split_covariance_intersection')
"""Fusion methods of ``update``, named as the fuser's ``fusion`` parameter names them."""

OMEGA_EDGE = 1e-9
"""The fusion weight is searched in ``[OMEGA_EDGE, 1 - OMEGA_EDGE]``."""

_OMEGA_STEPS = 60
"""Bisection steps on the weight: the bracket shrinks below 1e-18."""


def _range_scale_fields(range_scale, limit, shape):
    """Return ``Views.range_scale`` and its bearing limit broadcast to ``shape``, checked."""
    range_scale = np.asarray(range_scale, dtype=np.float64)
    limit = np.asarray(limit, dtype=np.float64)
    if range_scale.ndim not in (1, 2) or range_scale.shape[-1] != 3 or limit.ndim > 1:
        raise ValueError(f'range_scale must have shape (3,) or (N, 3) and its bearing limit '
                         f'() or (N,), got {range_scale.shape} and {limit.shape}')
    try:
        range_scale = np.broadcast_to(range_scale, shape + (3,)).copy()
        limit = np.broadcast_to(limit, shape).copy()
    except ValueError:
        raise ValueError(f'range_scale disagrees on N: {range_scale.shape}, {shape}') from None
    if not (np.all(np.isfinite(range_scale)) and np.all((limit > 0.0) & (limit <= np.pi))):
        raise ValueError('range_scale must be finite and its bearing limit in (0, pi]')
    if not np.all(range_scale_valid(range_scale, limit)):
        raise ValueError(f'range scale factor below {MIN_SCALE} inside the bearing limit')
    return range_scale, limit


def range_scale_valid(range_scale: ArrayLike, limit: ArrayLike) -> NDArray[np.bool_]:
    """
    Return which rows hold a range scale ``Views`` accepts.

    Parameters
    ----------
    range_scale : array_like, shape (N, 3)
        ``(q0, q1, q2)`` per row.
    limit : array_like, shape (N,)
        Bearing limit [rad].

    Returns
    -------
    ndarray of bool, shape (N,)
        Finite coefficients, a limit in (0, pi], and a factor
        ``1 + q0 + q1 b + q2 b^2`` of at least ``range_scale.MIN_SCALE`` at nine
        bearings spread over ``[-limit, limit]``.

    """
    q = np.asarray(range_scale, dtype=np.float64).reshape(-1, 3)
    limit = np.asarray(limit, dtype=np.float64)
    with np.errstate(invalid='ignore', over='ignore'):
        b = np.clip(limit, 0.0, np.pi)[:, None] * np.linspace(-1.0, 1.0, 9)
        factor = 1.0 + q[:, :1] + b * (q[:, 1:2] + q[:, 2:] * b)
        return (np.isfinite(q).all(axis=1) & (limit > 0.0) & (limit <= np.pi)
                & (factor >= MIN_SCALE).all(axis=1))


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
    range_scale : ndarray, shape (N, 3)
        ``(q0, q1, q2)``: a range view measures ``|m - s_xy| (1 + q0 + q1 b + q2 b^2)``,
        ``b`` the landmark's bearing from the sensor clipped to
        ``[-range_scale_bearing_limit, range_scale_bearing_limit]`` (a camera's range
        scale over its image, ``range_scale``); zero by default, ignored by bearing views.
    range_scale_bearing_limit : ndarray, shape (N,)
        Half the sensor's field of view [rad], in (0, pi]; pi by default.

    Raises
    ------
    ValueError
        On a wrong shape or kind, a non-finite value, ``R <= 0``, ``R_bias < 0``, a
        ``P_s`` that is not symmetric positive semi-definite, a bearing limit outside
        (0, pi] or a range scale factor below ``range_scale.MIN_SCALE`` inside it.

    """

    kind: NDArray[np.int64]
    s: NDArray[np.float64]
    P_s: NDArray[np.float64]
    y: NDArray[np.float64]
    R: NDArray[np.float64]
    # Any array_like on input: __post_init__ makes every field an array (0.0 too).
    R_bias: NDArray[np.float64] = 0.0  # type: ignore[assignment]
    range_scale: NDArray[np.float64] = NO_RANGE_SCALE  # type: ignore[assignment]
    range_scale_bearing_limit: NDArray[np.float64] = np.pi  # type: ignore[assignment]

    if TYPE_CHECKING:
        # The constructor takes array_like fields (what __post_init__ converts).
        def __init__(self, kind: ArrayLike, s: ArrayLike, P_s: ArrayLike, y: ArrayLike,
                     R: ArrayLike, R_bias: ArrayLike = 0.0,
                     range_scale: ArrayLike = NO_RANGE_SCALE,
                     range_scale_bearing_limit: ArrayLike = np.pi) -> None:
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
        scale, limit = _range_scale_fields(self.range_scale, self.range_scale_bearing_limit,
                                           shape)
        for name, value in (('kind', kind), ('s', s), ('P_s', P_s), ('y', y), ('R', R),
                            ('R_bias', R_bias), ('range_scale', scale),
                            ('range_scale_bearing_limit', limit)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        """Return the number of views ``N``."""
        return self.kind.shape[0]

    def __getitem__(self, index: Union[int, np.integer[Any], slice, NDArray[Any]]) -> 'Views':
        """Return the views selected by an index, a slice or a mask, as a batch."""
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        picked = {f.name: getattr(self, f.name)[index] for f in _FIELDS}
        if picked['kind'].ndim != 1:
            return Views(**picked)      # not a selection of rows: let the checks say so
        return Views._checked(picked)

    @staticmethod
    def concatenate(batches: Iterable['Views']) -> 'Views':
        """Return one batch holding the views of several, in order."""
        batches = list(batches)
        return Views._checked({f.name: np.concatenate([getattr(b, f.name) for b in batches])
                               for f in _FIELDS})

    @staticmethod
    def _checked(values: Dict[str, NDArray[Any]]) -> 'Views':
        """
        Return views made of the fields of checked views, without checking them again.

        For rows picked or joined, and within ``core`` for a bias set to zero: the
        checks hold by construction (they cost more than the updates of one view).
        """
        views = object.__new__(Views)
        for name, value in values.items():
            value = np.asarray(value)
            value.flags.writeable = False
            object.__setattr__(views, name, value)
        return views


_FIELDS = fields(Views)


def views_from_robot(kind: ArrayLike, pose: ArrayLike, P_pose: ArrayLike, y: ArrayLike,
                     R: ArrayLike, R_bias: ArrayLike = 0.0,
                     sensor_pose: Optional[ArrayLike] = None,
                     range_scale: Tuple[ArrayLike, ArrayLike] = (NO_RANGE_SCALE, np.pi)
                     ) -> Views:
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
    range_scale : tuple
        ``Views.range_scale`` and ``Views.range_scale_bearing_limit``.

    Returns
    -------
    Views

    Raises
    ------
    ValueError
        As ``Views`` does.

    """
    s, P_s = sensor_in_world(pose, P_pose, sensor_pose)
    return Views(kind, s, P_s, y, R, R_bias, *range_scale)


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


def observe_views(views: Views, m: ArrayLike) -> NDArray[np.float64]:
    """
    Predict views at landmarks: ``observe_view`` with each range view's scale.

    A range view predicts ``rho (1 + q0 + q1 b + q2 b^2)``, ``rho`` and ``b`` the range
    and the bearing (clipped to the view's limit) of ``m`` from the sensor
    (``Views.range_scale``); a bearing view predicts the bearing.

    Parameters
    ----------
    views : Views
        ``N`` views.
    m : array_like, shape (2,) or (N, 2) [m]
        One landmark for all views or one per view.

    Returns
    -------
    h : ndarray, shape (N,)

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to its sensor.

    """
    z = np.broadcast_to(sensors.observe(views.s, m), views.s.shape[:-1] + (2,))
    factor, _ = _scale_factor(views, z[:, 1])
    return np.where(views.kind == RANGE, z[:, 0] * factor, z[:, 1])


def observe_views_jacobians(views: Views, m: ArrayLike
                            ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the Jacobians of ``observe_views``.

    For a range view, ``d h = f d rho + rho f'(b) d b`` (``f`` the scale factor; ``f'``
    is 0 where the bearing is clipped); for a bearing view the bearing's row.

    Parameters
    ----------
    views : Views
        ``N`` views.
    m : array_like, shape (2,) or (N, 2) [m]
        One landmark for all views or one per view.

    Returns
    -------
    J_h_s : ndarray, shape (N, 1, 3)
    J_h_m : ndarray, shape (N, 1, 2)

    Raises
    ------
    ValueError
        If a landmark is closer than ``sensors.MIN_RANGE`` to its sensor.

    """
    shape = views.s.shape[:-1]
    z = np.broadcast_to(sensors.observe(views.s, m), shape + (2,))
    J_z_s, J_z_m = sensors.observe_jacobians(views.s, m)
    J_z_s, J_z_m = np.broadcast_to(J_z_s, shape + (2, 3)), np.broadcast_to(J_z_m, shape + (2, 2))
    factor, slope = _scale_factor(views, z[:, 1])
    is_range = (views.kind == RANGE)[:, None]
    J_h_s = np.where(is_range, factor[:, None] * J_z_s[:, 0]
                     + (z[:, 0] * slope)[:, None] * J_z_s[:, 1], J_z_s[:, 1])
    J_h_m = np.where(is_range, factor[:, None] * J_z_m[:, 0]
                     + (z[:, 0] * slope)[:, None] * J_z_m[:, 1], J_z_m[:, 1])
    return J_h_s[:, None, :], J_h_m[:, None, :]


def _scale_factor(views, bearing):
    """Return each view's range scale factor at ``bearing`` and its derivative."""
    limit = views.range_scale_bearing_limit
    b = np.clip(bearing, -limit, limit)
    q = views.range_scale
    factor = 1.0 + q[:, 0] + b * (q[:, 1] + q[:, 2] * b)
    slope = np.where(np.abs(bearing) < limit, q[:, 1] + 2.0 * q[:, 2] * b, 0.0)
    return factor, slope


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
    residual = residuals(views, m)
    J_h_s, J_h_m = observe_views_jacobians(views, m)
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
    residual = views.y - observe_views(views, m)
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
