"""
Simulated wheel odometry with a documented noise model (ROS-free).

The true motion between two odometry stamps (the path's poses at both) is decomposed
into ``rot1``, ``trans``, ``rot2`` (Probabilistic Robotics, ch. 5.4) and each part gets an
independent zero-mean Gaussian error with the variances of the odometry model

- ``var(rot1) = a1 rot1^2 + a2 trans^2``
- ``var(trans) = a3 trans^2 + a4 (rot1^2 + rot2^2)``
- ``var(rot2) = a1 rot2^2 + a2 trans^2``

(the same model ``landmark_ros.localizer.motion.odometry_noise`` linearises); the noisy
steps are chained from the origin of the odometry frame, so the odometry pose drifts as
wheel odometry does. With the same alphas in the localizer, its motion model is exact
up to the linearisation.
"""

import math

from landmark_ros.localizer import motion
import numpy as np


def wheel_odometry(true_poses, alphas, generator):
    """
    Return the odometry poses of a true path, with the noise of the odometry model.

    Parameters
    ----------
    true_poses : ndarray, shape (K, 3)
        True poses at the odometry stamps.
    alphas : sequence of 4 float
        ``(a1, a2, a3, a4)`` of the model (module docstring).
    generator : numpy.random.Generator
        Source of the errors.

    Returns
    -------
    ndarray, shape (K, 3)
        Odometry poses in the odometry frame, the first at the origin.

    """
    a1, a2, a3, a4 = alphas
    odom = np.zeros((len(true_poses), 3))
    for k in range(1, len(true_poses)):
        rot1, trans, rot2 = motion.decompose(motion.between(true_poses[k - 1], true_poses[k]))
        t2, r1, r2 = trans * trans, rot1 * rot1, rot2 * rot2
        rot1 += generator.normal(0.0, math.sqrt(a1 * r1 + a2 * t2))
        trans += generator.normal(0.0, math.sqrt(a3 * t2 + a4 * (r1 + r2)))
        rot2 += generator.normal(0.0, math.sqrt(a1 * r2 + a2 * t2))
        step = np.array([trans * math.cos(rot1), trans * math.sin(rot1), rot1 + rot2])
        odom[k] = motion.compose(odom[k - 1], step)
    return odom


class WheelOdometry:
    """
    Wheel odometry of one robot, one true pose at a time (``wheel_odometry`` step by step).

    Parameters
    ----------
    alphas : sequence of 4 float
        The odometry model's parameters.
    generator : numpy.random.Generator
        Source of the errors.

    """

    def __init__(self, alphas, generator):
        self.alphas = tuple(alphas)
        self.generator = generator
        self._true = None
        self.pose = np.zeros(3)

    def step(self, true_pose):
        """Move to ``true_pose`` (3,); return the odometry pose (3,), the first the origin."""
        true_pose = np.asarray(true_pose, dtype=np.float64)
        if self._true is not None:
            pair = np.stack([self._true, true_pose])
            step = wheel_odometry(pair, self.alphas, self.generator)[1]
            self.pose = motion.compose(self.pose, step)
        self._true = true_pose
        return self.pose.copy()
