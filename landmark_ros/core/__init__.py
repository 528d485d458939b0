"""
ROS-free landmark mathematics: poses, range-bearing sensors, Gaussians.

Everything here needs numpy only: no rclpy, no message packages, so the same code
serves the nodes, the offline tools and the tests.

Conventions
-----------
pose
    ``(x [m], y [m], theta [rad])``, theta wrapped to ``[-pi, pi)``.
point, landmark ``m``
    ``(x [m], y [m])``.
observation ``z``
    ``(range [m], bearing [rad])``; the bearing is counter-clockwise from the
    sensor's x axis (REP-103). Range first, bearing second (GTSAM orders them
    the other way round; we do not).
shapes
    A single item has shape ``(n,)``, a batch ``(N, n)``. Every function takes
    either and returns the same kind; a batch of one stays a batch. Jacobians are
    ``(n_out, n_in)`` or ``(N, n_out, n_in)``, covariances ``(n, n)`` or
    ``(N, n, n)``, always float64. Single items broadcast against batches.
Jacobians
    Plain partial derivatives with respect to the components ``(x, y, theta)``
    (not derivatives on the SE(2) manifold, as manif has them), named
    ``J_out_in``: ``J_m_pose`` is d m / d pose, so chains read
    ``J_z_x = J_z_m @ J_m_x``.
covariances
    ``P_*`` for states, ``R`` for sensor noise, ``S`` for innovations. Standard
    deviations appear only in parameters; the code works with variances.
    Accepted range (``covariance.covariance_range_status``): variances from
    ``MIN_VARIANCE`` = 1e-12 to ``MAX_VARIANCE`` = 1e12 m^2, condition number up to
    ``MAX_CONDITION`` = 1e9; inside it every 2x2 closed form is scaled and neither
    overflows nor underflows.
time
    Stamps inside the core are integer nanoseconds (``stamp_ns``, int64).

Modules
-------
pose2      SE(2) composition (+), inverse (-), ``between`` and point transforms.
sensors    Range-bearing, range-only and bearing-only models and their inverses.
gaussian   Product of Gaussians, covariance intersection and split CI.
gating     Mahalanobis distance and the chi-square gate.
covariance Covariance checks and the accepted range.
landmarks  The chapter's operations with full uncertainty propagation.
ellipse    Geometry of the k-sigma contour of a 2D Gaussian.
landmark_map  ``LandmarkMap``: fusion by landmark ID, gating, confirmation.
curvature  Second derivatives of range and bearing; relative curvatures of a fit.

"""
