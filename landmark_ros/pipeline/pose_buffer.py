"""
A bounded, time-ordered buffer of uncertain poses with interpolation (ROS-free).

Stamps are integer nanoseconds, so bracketing comparisons are exact.
"""

import bisect
from dataclasses import dataclass
from typing import List, Optional, Tuple

from landmark_ros.core.pose2 import wrap_angle
import numpy as np
from numpy.typing import ArrayLike, NDArray


FOUND = 'found'
WAIT = 'wait'
TOO_OLD = 'too_old'


@dataclass(frozen=True)
class Lookup:
    """
    Result of ``PoseBuffer.lookup``.

    ``status`` is ``FOUND`` (``pose`` and ``P_pose`` set), ``WAIT`` (the stamp is newer
    than every pose: a later pose may still bracket it) or ``TOO_OLD`` (older than
    the buffer by more than the allowed gap: it will never be bracketed).
    """

    status: str
    pose: Optional[NDArray[np.float64]] = None
    P_pose: Optional[NDArray[np.float64]] = None


def interpolate(
        pose0: NDArray[np.float64], P0: NDArray[np.float64],
        pose1: NDArray[np.float64], P1: NDArray[np.float64],
        fraction: float,
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Interpolate between two poses: position linear, heading on the shortest arc.

    Parameters
    ----------
    pose0, pose1 : ndarray, shape (3,)
        Poses at the two bracketing stamps.
    P0, P1 : ndarray, shape (3, 3)
        Their covariances.
    fraction : float
        0 gives ``pose0``, 1 gives ``pose1``.

    Returns
    -------
    pose : ndarray, shape (3,)
    P_pose : ndarray, shape (3, 3)
        ``(1 - fraction) P0 + fraction P1``, positive semi-definite when both are.

    """
    x0, y0, theta0 = pose0.tolist()
    x1, y1, theta1 = pose1.tolist()
    # Plain floats: this runs once per observation message, numpy scalars cost more.
    theta = wrap_angle(theta0 + fraction * wrap_angle(theta1 - theta0))
    pose = np.array([x0 + fraction * (x1 - x0), y0 + fraction * (y1 - y0), theta])
    return pose, (1.0 - fraction) * P0 + fraction * P1


class PoseBuffer:
    """
    Keep the poses of the last ``duration_ns`` and look them up by stamp.

    Parameters
    ----------
    duration_ns : int
        Poses older than the newest by more than this are dropped.
    max_gap_ns : int
        A stamp at most this far outside the buffer takes the nearest pose.
    max_size : int
        Hard bound on the number of poses kept.

    """

    def __init__(self, duration_ns: float, max_gap_ns: float, max_size: int = 10000) -> None:
        self.duration_ns = int(duration_ns)
        self.max_gap_ns = int(max_gap_ns)
        self.max_size = int(max_size)
        self.clear()

    def clear(self) -> None:
        """Forget every pose."""
        self._stamps: List[int] = []
        self._poses: List[NDArray[np.float64]] = []
        self._covariances: List[NDArray[np.float64]] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def stamps_ns(self) -> Tuple[int, ...]:
        """Return the stamps of the poses held [ns], oldest first."""
        return tuple(self._stamps)

    @property
    def newest_ns(self) -> Optional[int]:
        """Stamp of the newest pose, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, pose: ArrayLike, P_pose: ArrayLike) -> None:
        """
        Append a pose newer than every pose held.

        Parameters
        ----------
        stamp_ns : int
            Stamp [ns].
        pose : ndarray, shape (3,)
            Pose (x, y, theta).
        P_pose : ndarray, shape (3, 3)
            Covariance of the pose.

        Raises
        ------
        ValueError
            If ``stamp_ns`` is not newer than the newest pose.

        """
        if self._stamps and stamp_ns <= self._stamps[-1]:
            raise ValueError(f'pose stamp {stamp_ns} is not newer than {self._stamps[-1]}')
        self._stamps.append(int(stamp_ns))
        self._poses.append(np.array(pose, dtype=np.float64))
        self._covariances.append(np.array(P_pose, dtype=np.float64))
        cut = bisect.bisect_left(self._stamps, stamp_ns - self.duration_ns)
        cut = max(cut, len(self._stamps) - self.max_size)
        if cut > 0:
            del self._stamps[:cut], self._poses[:cut], self._covariances[:cut]

    def lookup(self, stamp_ns: int, final: bool = False) -> Lookup:
        """
        Return the pose at ``stamp_ns``.

        Interpolates between the two poses that bracket the stamp. A stamp at most
        ``max_gap_ns`` older than the buffer takes the oldest pose. A stamp newer than
        every pose waits for the next pose (better to interpolate than to hold the
        last pose) unless ``final``: then one within ``max_gap_ns`` takes the newest.

        Parameters
        ----------
        stamp_ns : int
            Stamp [ns].
        final : bool
            True when the observation will not wait any longer.

        Returns
        -------
        Lookup

        """
        if not self._stamps:
            return Lookup(WAIT)
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            return Lookup(FOUND, self._poses[i].copy(), self._covariances[i].copy())
        if i == len(self._stamps):
            if final and stamp_ns - self._stamps[-1] <= self.max_gap_ns:
                return Lookup(FOUND, self._poses[-1].copy(), self._covariances[-1].copy())
            return Lookup(WAIT)
        if i == 0:
            if self._stamps[0] - stamp_ns <= self.max_gap_ns:
                return Lookup(FOUND, self._poses[0].copy(), self._covariances[0].copy())
            return Lookup(TOO_OLD)
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        pose, P_pose = interpolate(self._poses[i - 1], self._covariances[i - 1],
                                   self._poses[i], self._covariances[i],
                                   (stamp_ns - t0) / (t1 - t0))
        return Lookup(FOUND, pose, P_pose)
