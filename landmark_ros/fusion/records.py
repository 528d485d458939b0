"""
The records and pure functions of ``LandmarkMap``: snapshots, update results, gating.

``gate_due`` is the refresh schedule of a landmark's gate reference; ``agreeing`` finds
the observations that confirm (or rebuild) a landmark.
"""

from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Deque, Dict, List, Mapping, NamedTuple, Sequence, Tuple

from landmark_ros.core.arrays import mahalanobis_sq_2x2, symmetrise
from landmark_ros.core.covariance import MIN_VARIANCE
from landmark_ros.fusion import compiled
from landmark_ros.fusion.methods import Rows
from landmark_ros.fusion.source_sums import entries, Estimates
import numpy as np
from numpy.typing import NDArray

GATE_BITS = 2
"""A landmark's gate reference is refreshed 2 ** GATE_BITS times per doubling of its
observations (every observation up to 2 ** (GATE_BITS + 1) - 1)."""


def gate_due(observations: NDArray[np.int64]) -> NDArray[np.bool_]:
    """
    Return whether a landmark's gate reference is refreshed once it has ``observations``.

    Every observation up to ``2 ** (GATE_BITS + 1) - 1``, then ``2 ** GATE_BITS`` times
    per doubling: the reference holds at least 4/5 of the current information, and
    refreshing it (a fold) costs next to nothing per observation for a landmark seen
    thousands of times.
    """
    n = np.asarray(observations, dtype=np.int64)
    length = np.frexp(np.maximum(n, 1).astype(np.float64))[1].astype(np.int64)  # bit length
    step = np.left_shift(1, np.maximum(length - (GATE_BITS + 1), 0))
    return n % step == 0


class MapSnapshot(NamedTuple):
    """The confirmed landmarks, sorted by ID (``LandmarkMap.snapshot``)."""

    ids: NDArray[np.int64]
    """Landmark IDs, int64, shape (K,)."""
    m: NDArray[np.float64]
    """Means, shape (K, 2) [m]."""
    P: NDArray[np.float64]
    """Total covariances, shape (K, 2, 2) [m^2]."""
    P_dep: NDArray[np.float64]
    """Their dependent parts, shape (K, 2, 2) [m^2]."""
    observations: NDArray[np.int64]
    """Observations fused into each, int64, shape (K,)."""


def _no_ids():
    return np.empty(0, np.int64)


@dataclass
class UpdateResult:
    """What one ``LandmarkMap.update`` did, for counters and logs."""

    accepted: Counter[str] = field(default_factory=Counter)
    """Observations fused into confirmed landmarks, by source."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Observations gated out or left out of a confirmation, by source."""
    confirmed: List[int] = field(default_factory=list)
    """IDs that became landmarks."""
    reinitialised: List[int] = field(default_factory=list)
    """IDs rebuilt from their recent observations."""
    changed_ids: NDArray[np.int64] = field(default_factory=_no_ids, compare=False)
    """IDs (int64, sorted, unique) whose published estimate changed in this update;
    not part of ``==`` (an array)."""

    @property
    def changed(self) -> bool:
        """Whether the confirmed map changed."""
        return bool(self.accepted or self.confirmed or self.reinitialised)


@dataclass(frozen=True)
class Observation:
    """One observation kept for a confirmation or a rebuild."""

    z: np.ndarray
    R_ind: np.ndarray
    R_dep: np.ndarray
    source: str
    stamp_ns: int


@dataclass(frozen=True)
class Batch:
    """One ``update`` call's rows: independent and dependent parts, global source codes."""

    z: np.ndarray
    R_ind: np.ndarray
    R_dep: np.ndarray
    names: list
    codes: np.ndarray
    stamps_ns: np.ndarray
    taken: np.ndarray
    """Rows fused into confirmed landmarks so far (bool), counted by source at the end."""

    @staticmethod
    def of(count: int, rows: Tuple[Any, Any, Any, Any], sources: Tuple[Any, Any],
           names: List[str], source_code: Callable[[str], int]) -> 'Batch':
        """
        Return ``LandmarkMap.update``'s input as a batch of ``count`` rows.

        ``rows``: ``z, R, R_dep, stamp_ns``, ``sources``: ``source, source_index``, as
        ``update`` takes them. New source names are registered by ``source_code`` in
        the order they first appear (as row by row would); ``names`` by code.
        """
        source, source_index = sources
        z = np.asarray(rows[0], dtype=np.float64).reshape(-1, 2)
        R = np.asarray(rows[1], dtype=np.float64).reshape(-1, 2, 2)
        R_dep = np.zeros_like(R) if rows[2] is None else np.asarray(
            rows[2], dtype=np.float64).reshape(-1, 2, 2)
        stamps_ns = np.asarray(rows[3])
        if not (np.issubdtype(stamps_ns.dtype, np.integer) or stamps_ns.size == 0):
            raise ValueError(f'stamp_ns must be integer nanoseconds, got {stamps_ns.dtype}')
        stamps_ns = np.broadcast_to(stamps_ns.astype(np.int64), (count,))
        if isinstance(source, str) and source_index is None:
            codes = np.full(count, source_code(source), np.int64)
        else:
            if source_index is None:
                given, inverse = np.unique(np.asarray(source, dtype=str), return_inverse=True)
            else:
                given = np.array([str(name) for name in source], dtype=object)
                inverse = np.asarray(source_index, dtype=np.int64)
            inverse = inverse.reshape(-1)
            if len(inverse) != count or (count and not (
                    0 <= inverse.min() and inverse.max() < len(given))):
                raise ValueError(f'source_index must hold {count} indices into {len(given)} '
                                 'sources')
            used, first = np.unique(inverse, return_index=True)
            by_name = np.zeros(len(given), np.int64)
            for k in used[np.argsort(first, kind='stable')].tolist():
                by_name[k] = source_code(str(given[k]))
            codes = by_name[inverse]
        # The one conversion to the independent part.
        return Batch(z, R - R_dep, R_dep, names, codes, stamps_ns, np.zeros(count, bool))

    def observation(self, i: int) -> Observation:
        """Return row ``i`` as an ``Observation``."""
        return Observation(self.z[i], self.R_ind[i], self.R_dep[i],
                           self.names[self.codes[i]], int(self.stamps_ns[i]))

    def rows(self, rows: NDArray[np.int64], positions: NDArray[np.int64]) -> Rows:
        """Return the rows at ``positions`` as ``Rows`` of the landmark rows ``rows``."""
        return Rows(rows, self.codes[positions], *(
            x.take(positions, axis=0) for x in (self.z, self.R_ind, self.R_dep)))


def stack(observations: Sequence[Observation]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``z, R_ind, R_dep`` of a list of observations as arrays."""
    return (np.array([obs.z for obs in observations]),
            np.array([obs.R_ind for obs in observations]),
            np.array([obs.R_dep for obs in observations]))


def agreeing(observations: List[Observation], threshold: float,
             fuse_rows: Callable[..., Any], method: str = '') -> List[Observation]:
    """
    Return the largest subset of observations that agree with one another.

    The seed is the observation that passes the pairwise gate with the most others
    (latest on ties); its partners join in arrival order while each passes the gate
    against the estimate fused so far. The seed always belongs to its own subset
    (it is never gated out), so the subset is never empty, even when distances are
    NaN (degenerate covariances). ``method``: the name of ``fuse_rows``'s method; split
    CI's loop ``compiled.agree`` runs once it is loaded (the same bits).
    """
    if not observations:
        return []
    z, R_ind, R_dep = stack(observations)
    R_ind, R_dep = symmetrise(R_ind), symmetrise(R_dep)
    R = R_ind + R_dep
    d = z[:, None, :] - z[None, :, :]
    S = R[:, None] + R[None, :]
    d2 = mahalanobis_sq_2x2(d[..., 0], d[..., 1], *entries(S))
    agree = d2 <= threshold
    np.fill_diagonal(agree, True)
    votes = agree.sum(axis=1)
    seed = len(observations) - 1 - int(np.argmax(votes[::-1]))
    members = np.flatnonzero(agree[seed])
    keep = None
    if method == 'split_covariance_intersection':
        keep = compiled.agree(z, np.column_stack(entries(R_ind) + entries(R_dep)), members,
                              seed, threshold)
    if keep is not None:
        return [observations[i] for i in members[keep].tolist()]
    members = members.tolist()
    first = members[0]
    cluster = [observations[first]]
    m, P_ind, P_dep = z[first:first + 1], R_ind[first:first + 1], R_dep[first:first + 1]
    for i in members[1:]:
        diff = z[i] - m[0]
        S = P_ind[0] + P_dep[0] + R[i]
        if i != seed and not mahalanobis_sq_2x2(diff[0], diff[1], *entries(S)) <= threshold:
            continue
        m, P_ind, P_dep = fuse_rows(m, P_ind, P_dep, z[i:i + 1], R_ind[i:i + 1],
                                    R_dep[i:i + 1])
        cluster.append(observations[i])
    return cluster


@dataclass(frozen=True)
class Checkpoint:
    """What an update of some rows can change (for an undo)."""

    count: int
    rows: NDArray[np.int64]
    arrays: Dict[str, np.ndarray]
    seen: Dict[str, NDArray[np.bool_]]
    buffers: Dict[int, Deque[Observation]]
    sources: List[str]
    method: Any


def parse_record(record: Mapping[str, Any]) -> Tuple[Estimates, Tuple[int, int], Tuple[int, int]]:
    """
    Return the estimate (one landmark), counts and stamps of a ``to_records`` record.

    Raises KeyError, TypeError or ValueError when it is malformed or not finite.
    """
    P = np.array(record['covariance'], dtype=np.float64).reshape(2, 2)
    P_dep = np.array(record['covariance_dependent'], dtype=np.float64).reshape(2, 2)
    mean = np.array(record['mean'], dtype=np.float64).reshape(2)
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(P_dep)) and np.all(np.isfinite(mean))):
        raise ValueError(f"landmark {record['id']}: non-finite values")
    stamps = []
    for value in (record['first_stamp_ns'], record['last_stamp_ns']):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise ValueError(f'expected an integer, got {value!r}')
        stamps.append(int(value))
    counts = int(record['observations']), int(record.get('rejections', 0))
    return Estimates(mean, P - P_dep, P_dep), counts, (stamps[0], stamps[1])


def floored(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """
    Return 2x2 covariances whose smallest eigenvalue is at least ``MIN_VARIANCE``.

    An estimate fused from rows at the variance floor falls below it (two rows of
    1e-12 m^2 give 5e-13), yet a saved record must pass the checks of a live row
    (``core.covariance``'s accepted range) to load back. Below the floor the covariance
    gets ``(MIN_VARIANCE - lambda_min) I`` added, with a relative margin of 1e-9: larger,
    so still consistent; above it nothing changes, bit for bit.

    Parameters
    ----------
    P : ndarray, shape (N, 2, 2)
        Symmetric covariances [m^2].

    Returns
    -------
    ndarray, shape (N, 2, 2)

    """
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    lambda_min = 0.5 * (a + c) - np.hypot(0.5 * (a - c), b)
    low = lambda_min < MIN_VARIANCE
    if not low.any():
        return P
    P = P.copy()
    P[low] += ((MIN_VARIANCE * (1.0 + 1e-9) - lambda_min[low])[:, None, None] * np.eye(2))
    return P
