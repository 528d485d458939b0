"""
Accuracy and consistency of a landmark map against ground truth (ROS-free).

A consistent estimator's normalised estimation error squared (NEES) of a 2D
landmark is chi-square with 2 degrees of freedom, mean 2; the average NEES over
``K`` independent landmarks, times ``K``, is chi-square with ``2 K`` degrees of
freedom, which gives the interval an honest average NEES falls into.
"""

from dataclasses import dataclass
import math

from landmark_ros.core.gaussian import mahalanobis_sq
import numpy as np
from scipy import special


@dataclass(frozen=True)
class LandmarkResult:
    """One fused landmark against its true position."""

    id: int  # noqa: A003, the landmark ID as in the messages
    m: np.ndarray
    P: np.ndarray
    error_m: float
    nees: float
    observations: int = 0
    rejections: int = 0


@dataclass(frozen=True)
class Summary:
    """Accuracy and consistency over the landmarks of a map."""

    landmarks: int
    rmse_m: float
    anees: float
    anees_interval: tuple

    @property
    def consistent(self):
        """Whether the average NEES lies in its interval."""
        low, high = self.anees_interval
        return low <= self.anees <= high


def chi2_quantile(dof, probability):
    """
    Return a chi-square quantile for any number of degrees of freedom.

    ``scipy.special.chdtri`` on the upper tail, as ``chi2_threshold`` (which also
    checks its arguments and stops at 100 degrees of freedom).

    Parameters
    ----------
    dof : int
        Degrees of freedom.
    probability : float
        In (0, 1).

    Returns
    -------
    float

    """
    return float(special.chdtri(dof, 1.0 - probability))


def anees_interval(landmarks, dof=2, probability=0.95):
    """
    Return the two-sided interval of the average NEES of consistent estimates.

    Parameters
    ----------
    landmarks : int
        Independent estimates averaged.
    dof : int
        Dimension of each estimate.
    probability : float
        Mass of the interval.

    Returns
    -------
    (float, float)

    """
    total = landmarks * dof
    tail = 0.5 * (1.0 - probability)
    return (chi2_quantile(total, tail) / landmarks, chi2_quantile(total, 1.0 - tail) / landmarks)


def evaluate(ids, m, P, truth, observations=None, rejections=None):
    """
    Compare fused landmarks with their true positions.

    Parameters
    ----------
    ids : array_like of int, shape (K,)
        Landmark IDs; IDs without a true position are left out.
    m : array_like, shape (K, 2)
        Fused positions [m].
    P : array_like, shape (K, 2, 2)
        Their covariances.
    truth : dict
        ``id -> (x, y)`` true positions.
    observations, rejections : array_like of int, shape (K,), optional
        Per-landmark counts to carry into the results.

    Returns
    -------
    results : list of LandmarkResult
    summary : Summary

    """
    results = []
    for i, landmark_id in enumerate(np.asarray(ids).tolist()):
        if landmark_id not in truth:
            continue
        true = np.asarray(truth[landmark_id], dtype=np.float64)
        results.append(LandmarkResult(
            id=landmark_id, m=np.asarray(m[i]), P=np.asarray(P[i]),
            error_m=float(np.linalg.norm(np.asarray(m[i]) - true)),
            nees=float(mahalanobis_sq(true, m[i], P[i])),
            observations=int(observations[i]) if observations is not None else 0,
            rejections=int(rejections[i]) if rejections is not None else 0))
    if not results:
        return results, Summary(0, float('nan'), float('nan'), (float('nan'), float('nan')))
    errors = np.array([r.error_m for r in results])
    nees = np.array([r.nees for r in results])
    return results, Summary(len(results), float(np.sqrt(np.mean(errors ** 2))),
                            float(np.mean(nees)), anees_interval(len(results)))


def format_table(results, summary, title=''):
    """
    Return a plain-text table of the landmarks and the summary lines.

    Parameters
    ----------
    results : list of LandmarkResult
        From ``evaluate``.
    summary : Summary
        From ``evaluate``.
    title : str
        First line.

    Returns
    -------
    str

    """
    lines = [title] if title else []
    lines.append(f"{'id':>5} {'x [m]':>9} {'y [m]':>9} {'sd_x [cm]':>9} {'sd_y [cm]':>9} "
                 f"{'error [cm]':>10} {'NEES':>8} {'obs':>6} {'rej':>5}")
    for r in results:
        lines.append(
            f'{r.id:5d} {r.m[0]:9.3f} {r.m[1]:9.3f} {100 * math.sqrt(r.P[0, 0]):9.2f} '
            f'{100 * math.sqrt(r.P[1, 1]):9.2f} {100 * r.error_m:10.2f} {r.nees:8.2f} '
            f'{r.observations:6d} {r.rejections:5d}')
    low, high = summary.anees_interval
    verdict = 'consistent' if summary.consistent else 'NOT consistent'
    lines.append(f'RMSE {100 * summary.rmse_m:.2f} cm over {summary.landmarks} landmarks; '
                 f'average NEES {summary.anees:.2f}, 95 % interval [{low:.2f}, {high:.2f}]: '
                 f'{verdict}')
    return '\n'.join(lines)
