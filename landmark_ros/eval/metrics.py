"""
Accuracy and consistency of a landmark map against ground truth (ROS-free).

A consistent estimator's normalised estimation error squared (NEES) of a 2D
landmark is chi-square with 2 degrees of freedom, mean 2; the average NEES over
``K`` independent landmarks, times ``K``, is chi-square with ``2 K`` degrees of
freedom, which gives the interval an honest average NEES falls into.
"""

from dataclasses import dataclass
import math

from landmark_ros.core.gating import mahalanobis_sq
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


# Landmarks without IDs -------------------------------------------------------------------

def match_tracks(track_m, true_m, max_distance_m=float('inf')):
    """
    Match estimated tracks with true landmarks one to one at the smallest total distance.

    Parameters
    ----------
    track_m : array_like, shape (K, 2) [m]
        Track positions.
    true_m : array_like, shape (T, 2) [m]
        True landmark positions.
    max_distance_m : float
        Pairs farther apart stay unmatched.

    Returns
    -------
    ndarray of int, shape (K,)
        Index of each track's true landmark, -1 for none. Solved with
        ``scipy.optimize.linear_sum_assignment`` on the Euclidean distances.

    """
    from scipy.optimize import linear_sum_assignment
    track_m = np.asarray(track_m, np.float64).reshape(-1, 2)
    true_m = np.asarray(true_m, np.float64).reshape(-1, 2)
    match = np.full(len(track_m), -1, np.int64)
    if not len(track_m) or not len(true_m):
        return match
    distance = np.linalg.norm(track_m[:, None, :] - true_m[None, :, :], axis=-1)
    rows, columns = linear_sum_assignment(distance)
    near = distance[rows, columns] <= max_distance_m
    match[rows[near]] = columns[near]
    return match


def gospa(estimated_m, true_m, c=1.0, p=2.0, alpha=2.0):
    """
    Return the generalised optimal sub-pattern assignment (GOSPA) distance.

    ``d = (min_assignment sum d(x, y)^p + c^p / alpha (|X| + |Y| - 2 |assigned|))^(1/p)``
    with distances cut at ``c``; for ``alpha = 2`` this is localisation error plus
    ``c^p / 2`` per missed and per false landmark. Source: A. S. Rahmathullah,
    A. F. Garcia-Fernandez and L. Svensson, "Generalized optimal sub-pattern
    assignment metric", FUSION 2017.

    Parameters
    ----------
    estimated_m : array_like, shape (K, 2) [m]
        Estimated landmark positions.
    true_m : array_like, shape (T, 2) [m]
        True positions.
    c : float
        Cut-off distance [m].
    p : float
        Order, >= 1.
    alpha : float
        In (0, 2]; 2 for the assignment form above.

    Returns
    -------
    float
        GOSPA distance [m].

    """
    from scipy.optimize import linear_sum_assignment
    estimated_m = np.asarray(estimated_m, np.float64).reshape(-1, 2)
    true_m = np.asarray(true_m, np.float64).reshape(-1, 2)
    total = c ** p / alpha * (len(estimated_m) + len(true_m))
    if len(estimated_m) and len(true_m):
        distance = np.minimum(np.linalg.norm(
            estimated_m[:, None, :] - true_m[None, :, :], axis=-1), c)
        # Pairing costs d^p and saves the two c^p / alpha of leaving both unassigned.
        cost = distance ** p - 2.0 * c ** p / alpha
        rows, columns = linear_sum_assignment(np.minimum(cost, 0.0))
        total += float(np.minimum(cost[rows, columns], 0.0).sum())
    return float(max(total, 0.0) ** (1.0 / p))


def oracle_nearest(z, R, true_ids, true_m):
    """
    Return, per observation, the true landmark nearest by Mahalanobis distance.

    Parameters
    ----------
    z : array_like, shape (N, 2) [m]
        Observed landmark positions in the world.
    R : array_like, shape (N, 2, 2) [m^2]
        Their covariances.
    true_ids : array_like of int, shape (T,)
        True landmark IDs.
    true_m : array_like, shape (T, 2) [m]
        True positions (exact: the oracle knows the map).

    Returns
    -------
    ndarray of int, shape (N,)
        The ID of the nearest true landmark of each observation.

    """
    z = np.asarray(z, np.float64).reshape(-1, 2)
    R = np.asarray(R, np.float64).reshape(-1, 2, 2)
    true_m = np.asarray(true_m, np.float64).reshape(-1, 2)
    d2 = np.stack([np.atleast_1d(mahalanobis_sq(z, t, R)) for t in true_m], axis=1)
    return np.asarray(true_ids)[np.argmin(d2, axis=1)]


@dataclass(frozen=True)
class AssociationSummary:
    """How well a map built without IDs matches the truth (``evaluate_association``)."""

    association_accuracy: float
    """Sightings that went to the track matched to their true landmark, over all."""
    oracle_accuracy: float
    """Sightings whose nearest true landmark (Mahalanobis) is theirs, over all."""
    tracks_confirmed: int
    true_landmarks: int
    gospa_m: float
    """GOSPA distance of the confirmed tracks to the true landmarks (c = 1 m, p = 2)."""
    track_to_true: dict
    """Confirmed track ID -> matched true landmark ID."""
    confusion: dict
    """(true ID, true ID of the track it went to, or -1) -> sightings, for the wrong ones."""

    def to_dict(self):
        """Return the JSON fields."""
        return {'association_accuracy': self.association_accuracy,
                'oracle_accuracy': self.oracle_accuracy,
                'tracks_confirmed': self.tracks_confirmed,
                'true_landmarks': self.true_landmarks, 'gospa_m': self.gospa_m}


def evaluate_association(assigned_ids, true_ids, z, R, track_ids, track_m, truth,
                         max_distance_m=1.0):
    """
    Score the data association of sightings made without their IDs.

    Parameters
    ----------
    assigned_ids : array_like of int, shape (N,)
        The track ID each sighting got (-1: dropped).
    true_ids : array_like of int, shape (N,)
        Its true landmark.
    z : array_like, shape (N, 2) [m]
        The sightings in the world.
    R : array_like, shape (N, 2, 2) [m^2]
        Their covariances.
    track_ids : array_like of int, shape (K,)
        Confirmed track IDs.
    track_m : array_like, shape (K, 2) [m]
        Their positions.
    truth : dict
        ``id -> (x, y)`` true positions.
    max_distance_m : float
        Tracks farther than this from every true landmark match none.

    Returns
    -------
    AssociationSummary

    """
    true_list = sorted(truth)
    true_m = np.array([truth[i] for i in true_list], np.float64).reshape(-1, 2)
    track_ids = np.asarray(track_ids, np.int64)
    match = match_tracks(track_m, true_m, max_distance_m)
    pairs = zip(track_ids.tolist(), match.tolist())
    track_to_true = {int(t): int(true_list[j]) for t, j in pairs if j >= 0}
    assigned_ids = np.asarray(assigned_ids, np.int64)
    true_ids = np.asarray(true_ids, np.int64)
    went_to = np.array([track_to_true.get(i, -1) for i in assigned_ids.tolist()], np.int64)
    right = went_to == true_ids
    oracle = oracle_nearest(z, R, true_list, true_m) == true_ids if len(z) else right
    confusion = {}
    for a, b in zip(true_ids[~right].tolist(), went_to[~right].tolist()):
        confusion[(a, b)] = confusion.get((a, b), 0) + 1
    count = max(len(true_ids), 1)
    return AssociationSummary(float(right.sum() / count), float(oracle.sum() / count),
                              len(track_ids), len(true_list),
                              gospa(track_m, true_m), track_to_true, confusion)
