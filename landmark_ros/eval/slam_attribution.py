"""
Where a map's error comes from: a whole-map rigid transform, the rows' poses, the sensor.

ROS-free, numpy only; the evaluation of ``landmark_mrclam --slam``
(``mrclam.slam_attribution`` records what the loop placed and prints the study,
docs/slam.md "Where the map's error comes from"). Ground truth enters here only.

- ``rigid_fit``: the shift and rotation about a fixed centre (the start poses'
  centroid) that best map the true landmarks onto the estimated ones, and what is left.
- ``row_parts``: each placed row's error split into the part from the pose it was placed
  with (the same sighting placed from the true pose instead) and the sensor's part
  (placed from the true pose, against the true landmark).
- ``shift_nees``: the whole-map shift against the map's own covariance, with the
  landmarks' errors taken as fully shared (a frame error) and as independent.

Symbols: ``m`` a landmark position (2,) [m]; a pose ``(x, y, theta)`` [m, m, rad];
``local`` a landmark in the robot frame (2,) [m].
"""

from dataclasses import dataclass
from typing import Dict

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class RigidFit:
    """The best-fit rigid transform ``m_est ~ R(angle) (m_true - c) + c + shift``."""

    shift: NDArray[np.float64]
    """Translation [m], shape (2,)."""
    angle: float
    """Rotation about the centre [rad]."""
    center: NDArray[np.float64]
    """Centre of the rotation [m], shape (2,)."""
    residual: NDArray[np.float64]
    """``m_est`` less the transformed truth [m], shape (N, 2)."""

    @property
    def residual_rmse(self) -> float:
        """Return the root mean square of the residual distances [m]."""
        return float(np.sqrt(np.mean(np.sum(self.residual ** 2, axis=1))))


def _rotation(angle: float) -> NDArray[np.float64]:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def rigid_fit(m_est, m_true, center, rotate=True) -> RigidFit:
    """
    Return the least-squares rigid transform of the truth onto the estimate.

    Parameters
    ----------
    m_est, m_true : array_like, shape (N, 2)
        Estimated and true landmark positions [m], N >= 1 (N >= 2 to rotate).
    center : array_like, shape (2,)
        The rotation's centre [m] (the team's start poses' centroid).
    rotate : bool
        False: the shift alone (the mean error).

    Returns
    -------
    RigidFit

    Notes
    -----
    With ``p = m_true - c`` and ``q = m_est - c``, minimising ``sum |R p + t - q|^2``
    gives the angle of ``sum (p_i - pbar) x (q_i - qbar)`` against
    ``sum (p_i - pbar) . (q_i - qbar)`` and ``t = qbar - R pbar`` (2-D Procrustes).

    """
    q = np.asarray(m_est, np.float64).reshape(-1, 2)
    p = np.asarray(m_true, np.float64).reshape(-1, 2)
    c = np.asarray(center, np.float64).reshape(2)
    p, q = p - c, q - c
    pc, qc = p - p.mean(axis=0), q - q.mean(axis=0)
    angle = 0.0
    if rotate and len(p) >= 2:
        cross = float(np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0]))
        dot = float(np.sum(pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1]))
        angle = float(np.arctan2(cross, dot))
    R = _rotation(angle)
    shift = q.mean(axis=0) - R @ p.mean(axis=0)
    residual = q - (p @ R.T + shift)
    return RigidFit(shift, angle, c, residual)


def place(pose, local) -> NDArray[np.float64]:
    """Return world positions (N, 2) of robot-frame points ``local`` (N, 2) from poses (N, 3)."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    local = np.asarray(local, np.float64).reshape(-1, 2)
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return pose[:, :2] + np.stack([c * local[:, 0] - s * local[:, 1],
                                   s * local[:, 0] + c * local[:, 1]], axis=1)


def to_local(pose, m) -> NDArray[np.float64]:
    """Return robot-frame points (N, 2) of world points ``m`` (N, 2) seen from poses (N, 3)."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    d = np.asarray(m, np.float64).reshape(-1, 2) - pose[:, :2]
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def row_parts(m_row, pose_used, pose_true, m_true) -> Dict[str, NDArray[np.float64]]:
    """
    Split placed rows' errors into the pose's part and the sensor's part.

    Parameters
    ----------
    m_row : array_like, shape (N, 2)
        The rows as placed [m].
    pose_used : array_like, shape (N, 3)
        The pose each was placed with (the observer's).
    pose_true : array_like, shape (N, 3)
        The true pose at the sighting.
    m_true : array_like, shape (N, 2)
        The true landmark of each row [m].

    Returns
    -------
    dict
        ``pose`` (N, 2): ``m_row`` less the same sighting placed from the true pose;
        ``sensor`` (N, 2): that placement less ``m_true``; ``radial`` (N,) and
        ``tangential`` (N,): the sensor part along and across the line of sight from the
        true pose [m]; ``range`` (N,) [m]. ``pose + sensor`` is the row's error.

    """
    local = to_local(pose_used, m_row)
    from_truth = place(pose_true, local)
    sensor = from_truth - np.asarray(m_true, np.float64).reshape(-1, 2)
    sight = from_truth - np.asarray(pose_true, np.float64).reshape(-1, 3)[:, :2]
    rng = np.linalg.norm(sight, axis=1)
    u = sight / np.maximum(rng, 1e-12)[:, None]
    return {'pose': np.asarray(m_row, np.float64).reshape(-1, 2) - from_truth,
            'sensor': sensor, 'radial': np.sum(sensor * u, axis=1),
            'tangential': u[:, 0] * sensor[:, 1] - u[:, 1] * sensor[:, 0], 'range': rng}


def shift_nees(shift, P) -> Dict[str, float]:
    """
    Return the NEES of a whole-map shift under the map's covariances ``P`` (N, 2, 2).

    ``shared``: the landmarks' errors one common error (a frame error): the mean error's
    covariance is the mean of ``P``; ``independent``: it is ``sum P / N^2``. A shift
    with a small ``shared`` NEES (2 degrees of freedom: below 5.99 at 95 %) is inside
    what the map claims if its errors are one frame error.
    """
    shift = np.asarray(shift, np.float64).reshape(2)
    P = np.asarray(P, np.float64).reshape(-1, 2, 2)
    mean_P = P.mean(axis=0)
    return {'shared': float(shift @ np.linalg.solve(mean_P, shift)),
            'independent': float(shift @ np.linalg.solve(mean_P / len(P), shift))}
