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
range_scale : ``(q0, q1, q2)`` of a range view, shape (N, 3): it measures
    ``|m - s_xy| (1 + q0 + q1 b + q2 b^2)``, ``b`` the bearing of ``m`` clipped to
    ``range_scale_bearing_limit`` (shape (N,)); zero for a plain range sensor.
h : predicted value ``h(s, m)``, shape (1,) or (N, 1) (``observe_view``), or with the
    range scale, shape (N,) (``observe_views``).
J_h_s, J_h_m : its Jacobians, shapes (1, 3) and (1, 2) or (N, 1, 3) and (N, 1, 2).
R_eff : effective variance of a view at ``m``, ``R + R_bias + J_h_s P_s J_h_s^T``
    (the pose uncertainty pushed into the measurement), shape (N,).
R_dep : its dependent part ``R_bias + J_h_s P_s J_h_s^T``: the pose term is shared by
    every view made from that pose, the bias by every view of that sensor, shape (N,).
m : landmark in the world, shape (2,) or (N, 2) [m].
P_m, P_m_dep : its covariance and the dependent part of it, shape (2, 2) or
    (N, 2, 2) [m^2]; the independent part is ``P_m - P_m_dep``.

A residual is ``y - h`` with bearings wrapped to [-pi, pi).

The implementation is in four private modules, this one is the interface:
``_partial_model`` (kinds, ``Views``, the model ``h``, its Jacobians, residuals,
effective variances), ``_partial_geometry`` (closed-form intersections),
``_partial_init`` (delayed initialisation), ``_partial_update`` (EKF updates, iterated
where the model is not linear over the step) and ``_partial_consider`` (the update
with the view's sensor bias as a consider state).

"""

from landmark_ros.core._partial_consider import update_consider
from landmark_ros.core._partial_geometry import (intersect_circles, intersect_ray_circle,
                                                 intersect_rays, trilaterate)
from landmark_ros.core._partial_init import (dependent_covariance, Geometry, geometry,
                                             Initialisation, initialise, InitialiseParams)
from landmark_ros.core._partial_model import (BEARING, effective_variances, GATED, KIND_NAMES,
                                              Linearisation, linearise, METHODS,
                                              NO_RANGE_SCALE, observe_view,
                                              observe_view_jacobians, observe_views,
                                              observe_views_jacobians, OK, OMEGA_EDGE, RANGE,
                                              range_scale_valid, residuals, TOO_CLOSE,
                                              UPDATE_STATUS_NAMES, UPDATED, Views,
                                              views_from_robot, WAIT, WAIT_REASONS)
from landmark_ros.core._partial_update import (ITERATE_THRESHOLD, MAX_ITERATIONS, update,
                                               UpdateResult, view_omega)

__all__ = [
    'BEARING', 'dependent_covariance', 'effective_variances', 'GATED', 'Geometry', 'geometry',
    'Initialisation', 'initialise', 'InitialiseParams', 'intersect_circles',
    'intersect_ray_circle', 'intersect_rays', 'ITERATE_THRESHOLD', 'KIND_NAMES', 'Linearisation',
    'linearise', 'MAX_ITERATIONS', 'METHODS', 'NO_RANGE_SCALE', 'observe_view',
    'observe_view_jacobians', 'observe_views', 'observe_views_jacobians', 'OK',
    'OMEGA_EDGE', 'RANGE', 'range_scale_valid', 'residuals', 'TOO_CLOSE', 'trilaterate',
    'update',
    'update_consider', 'UPDATE_STATUS_NAMES', 'UPDATED', 'UpdateResult', 'view_omega', 'Views',
    'views_from_robot',
    'WAIT', 'WAIT_REASONS',
]
