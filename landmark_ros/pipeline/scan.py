"""
What a message's joint covariance needs, from the observer to the fuser (ROS-free).

The observer attaches a ``Scan`` to a landmark batch with rows without IDs; the
fuser's association (``fuser.tracks``) builds the rows' joint covariance from it
(``core.association.scan_covariance``).
"""

from dataclasses import dataclass
from typing import Optional

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Scan:
    """
    What the joint covariance of one message's rows needs (``association.scan_covariance``).

    Attributes
    ----------
    robot_xy : ndarray, shape (2,) [m]
        Robot position the message was observed from.
    P_pose : ndarray, shape (3, 3)
        Covariance of the robot pose (x [m], y [m], theta [rad]).
    R_bias : ndarray, shape (2, 2), optional
        Covariance of the sensor bias (range [m^2], bearing [rad^2]); None for none.
    sensor_xy : ndarray, shape (2,) [m], optional
        Sensor position in the world (with ``R_bias``).
    heading : float, optional
        Sensor heading in the world [rad] (the robot's plus the mount's): where the
        field of view points (the fuser's view, ``fuser.track_score``; not wrapped);
        None: unknown.
    range_scale_variance : float
        Variance of a range scale error shared by the message (dimensionless; with
        ``R_bias``): a row at range ``r`` is off by ``s r`` along its line of sight.

    """

    robot_xy: NDArray[np.float64]
    P_pose: NDArray[np.float64]
    R_bias: Optional[NDArray[np.float64]] = None
    sensor_xy: Optional[NDArray[np.float64]] = None
    heading: Optional[float] = None
    range_scale_variance: float = 0.0
