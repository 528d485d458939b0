"""
A map frame shared by the team and known up to a rigid transform (ROS-free, numpy only).

Real teams localise in one map: their pose errors are correlated in time and across
robots. This models the part they all share, the map frame's own error, drawn once
per run: the reported frame is the true one moved by a rotation ``eps`` about the
world origin and a translation ``tau``.

Symbols
-------
tau : ndarray, shape (2,)
    Translation error [m], ``N(0, s_t^2 I)``.
eps : float
    Rotation error [rad], ``N(0, s_r^2)``.
Sigma : ndarray, shape (3, 3)
    ``diag(s_t^2, s_t^2, s_r^2)``, the covariance of ``(tau, eps)``.
J : ndarray, shape (2, 2)
    ``[[0, -1], [1, 0]]``: ``eps J p`` is ``eps x p`` (a small rotation of ``p``).

Model and why split CI is exact under it
----------------------------------------
A robot at the true pose ``(p, theta)`` is reported at ``(R(eps) p + tau, theta +
eps)``. Its pose error is, to first order, ``e = (tau + eps J p, eps) = A(p) (tau,
eps)`` with ``A(p) = [[I, J p], [0, 1]]``, so its covariance is ``P_frame(p) = A(p)
Sigma A(p)^T`` (3x3, with translation-heading cross terms ``s_r^2 J p``): what the
robot reports on its pose topic (``covariance``).

A landmark ``l`` measured from the reported pose is placed at ``R(eps) l + tau``
(exactly: the whole scene is moved rigidly), so to first order every robot's
observation of ``l``, at every time, carries the same error ``tau + eps J l`` plus its
own sensor noise. The observer's dependent part is ``J_l_pose P_pose J_l_pose^T`` with
``J_l_pose = [I, J (l - p)]``; since ``[I, J (l - p)] A(p) = [I, J l]``, it is
``s_t^2 I + s_r^2 (J l)(J l)^T``, the covariance of ``tau + eps J l``, whatever the
robot and its pose. This is split CI's model: within a source the dependent parts are
one shared error (here constant over the run), across sources the dependent errors
are identical (correlation 1), the case CI bounds tightly: for two scalar estimates
with independent parts ``a``, ``b`` and a common dependent part ``d``, the optimal
weight ``omega = b / (a + b)`` makes split CI's covariance ``d + a b / (a + b)``,
the true one. Product of Gaussians, which averages the shared error down, is
over-confident; CI, which does not average the noise down, is conservative.
"""

from dataclasses import dataclass
import math

import numpy as np

J = np.array([[0.0, -1.0], [1.0, 0.0]])
"""The 90-degree rotation: ``eps J p`` is the first-order move of ``p`` by ``eps``."""


@dataclass(frozen=True)
class FrameError:
    """One draw of the map frame's rigid transform error and its covariance."""

    tau: np.ndarray
    """Translation [m], shape (2,)."""
    eps: float
    """Rotation about the world origin [rad]."""
    Sigma: np.ndarray
    """Covariance of ``(tau_x, tau_y, eps)``, shape (3, 3)."""

    def apply(self, pose):
        """
        Return a pose as the shifted frame reports it.

        Parameters
        ----------
        pose : array_like, shape (3,) or (N, 3)
            True ``(x [m], y [m], theta [rad])``.

        Returns
        -------
        ndarray, shape (3,) or (N, 3)
            ``(R(eps) p + tau, theta + eps)``; theta not wrapped.

        """
        pose = np.asarray(pose, dtype=np.float64)
        c, s = math.cos(self.eps), math.sin(self.eps)
        out = np.array(pose, dtype=np.float64, copy=True)
        out[..., 0] = c * pose[..., 0] - s * pose[..., 1] + self.tau[0]
        out[..., 1] = s * pose[..., 0] + c * pose[..., 1] + self.tau[1]
        out[..., 2] = pose[..., 2] + self.eps
        return out

    def covariance(self, pose):
        """
        Return the covariance of the pose error at a pose, ``A(p) Sigma A(p)^T``.

        Parameters
        ----------
        pose : array_like, shape (3,) or (N, 3)
            ``(x [m], y [m], theta [rad])``; only the position matters.

        Returns
        -------
        ndarray, shape (3, 3) or (N, 3, 3)
            Covariance of ``(x, y, theta)`` [m^2, m rad, rad^2].

        """
        return frame_covariance(pose, self.Sigma)

    def point_error(self, points):
        """
        Return the error of points as the shifted frame places them, ``R(eps) l + tau - l``.

        Parameters
        ----------
        points : array_like, shape (2,) or (N, 2)
            True positions [m].

        Returns
        -------
        ndarray, shape (2,) or (N, 2) [m]

        """
        points = np.asarray(points, dtype=np.float64)
        c, s = math.cos(self.eps), math.sin(self.eps)
        return points @ np.array([[c - 1.0, s], [-s, c - 1.0]]) + self.tau

    def point_covariance(self, points):
        """
        Return the first-order covariance of ``point_error``, ``Cov(tau + eps J l)``.

        Parameters
        ----------
        points : array_like, shape (2,) or (N, 2)
            Positions [m].

        Returns
        -------
        ndarray, shape (2, 2) or (N, 2, 2) [m^2]
            ``s_t^2 I + s_r^2 (J l)(J l)^T``.

        """
        points = np.asarray(points, dtype=np.float64)
        return frame_covariance(np.concatenate([points, np.zeros(points.shape[:-1] + (1,))],
                                               axis=-1), self.Sigma)[..., :2, :2]


def frame_covariance(pose, Sigma):
    """
    Return ``A(p) Sigma A(p)^T``, the first-order covariance of a frame error at ``p``.

    Parameters
    ----------
    pose : array_like, shape (3,) or (N, 3)
        ``(x [m], y [m], theta [rad])``.
    Sigma : array_like, shape (3, 3)
        Covariance of the frame's ``(tau_x, tau_y, eps)``.

    Returns
    -------
    ndarray, shape (3, 3) or (N, 3, 3)

    """
    pose = np.asarray(pose, dtype=np.float64)
    A = np.broadcast_to(np.eye(3), pose.shape[:-1] + (3, 3)).copy()
    A[..., :2, 2] = pose[..., :2] @ J.T
    P = A @ np.asarray(Sigma, dtype=np.float64) @ np.swapaxes(A, -1, -2)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def draw(generator, xy_stddev, yaw_stddev):
    """
    Draw a frame error.

    Parameters
    ----------
    generator : numpy.random.Generator
        Source of the three standard normal draws.
    xy_stddev : float
        ``s_t`` [m].
    yaw_stddev : float
        ``s_r`` [rad].

    Returns
    -------
    FrameError

    """
    sample = generator.standard_normal(3)
    return FrameError(np.array([xy_stddev * sample[0], xy_stddev * sample[1]]),
                      float(yaw_stddev * sample[2]),
                      np.diag([xy_stddev ** 2, xy_stddev ** 2, yaw_stddev ** 2]))
