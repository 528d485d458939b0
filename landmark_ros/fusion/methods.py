"""
The fusion methods of ``LandmarkMap``, each behind the same narrow interface.

A method turns accepted observations into landmark estimates; the map does everything
else (gating, confirmation, counts, stamps, checkpoints of its own arrays). What
crosses between the two is typed: ``Rows`` (observations) and ``Estimates``. Every
method has ``fuse`` (estimates with observations row by row: confirmation, merges),
``held`` (an estimate the way the method holds it), ``absorb`` (a batch's accepted rows),
``settle`` (estimates ``absorb`` left to later), ``start`` (a landmark from agreeing
observations), ``replace`` / ``merge`` / ``retire`` (estimates set, fused or dropped
by the map), ``records`` / ``load`` (method state in the saved map) and
``checkpoint`` / ``restore`` (undo of a failed update).

Sources: the product of Gaussians, the textbook chapter; covariance intersection,
Julier and Uhlmann, "A non-divergent estimation algorithm in the presence of unknown
correlations", ACC 1997; split covariance intersection, Julier and Uhlmann, "General
decentralized data fusion with covariance intersection", Handbook of Multisensor Data
Fusion, 2001.
"""

from dataclasses import dataclass
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Tuple

from landmark_ros.core.gaussian import (ci_2x2, covariance_intersection, fuse_2x2,
                                        split_covariance_intersection)
from landmark_ros.fusion.source_sums import entries, Estimates, one_source, SourceSums
import numpy as np
from numpy.typing import NDArray

Ints = NDArray[np.int64]


@dataclass(frozen=True)
class Rows:
    """Observations of landmarks, in arrival order."""

    rows: Ints
    """Each observation's landmark (a row of the map), shape (N,)."""
    codes: Ints
    """Each observation's source code, shape (N,)."""
    z: NDArray[np.float64]
    """Observed positions, shape (N, 2) [m]."""
    R_ind: NDArray[np.float64]
    """Independent parts of their covariances, shape (N, 2, 2) [m^2]."""
    R_dep: NDArray[np.float64]
    """Dependent parts, shape (N, 2, 2) [m^2]."""


def _ranks(groups):
    """Return how many earlier entries share each entry's group (its rank in it)."""
    order = np.argsort(groups, kind='stable')
    sorted_groups = groups[order]
    starts = np.ones(len(groups), bool)
    starts[1:] = sorted_groups[1:] != sorted_groups[:-1]
    first = np.maximum.accumulate(np.where(starts, np.arange(len(groups)), 0))
    rank = np.empty(len(groups), np.int64)
    rank[order] = np.arange(len(groups)) - first
    return rank


class Independent:
    """Product of Gaussians; the estimate is held as independent (``P_dep = 0``)."""

    name = 'independent'

    def __init__(self, independent_sources: bool = False) -> None:
        self.independent_sources = bool(independent_sources)
        """Whether the sources' dependent parts are independent of each other (split CI
        only: this method treats every part as independent, CI none)."""

    def reset(self) -> None:
        """Forget every landmark (nothing to forget)."""

    def fuse(self, m: NDArray[np.float64], P_ind: NDArray[np.float64],
             P_dep: NDArray[np.float64], z: NDArray[np.float64], R_ind: NDArray[np.float64],
             R_dep: NDArray[np.float64]) -> Estimates:
        """Fuse estimates with observations row by row (batches of (N, 2) and (N, 2, 2))."""
        m, P = fuse_2x2(m, entries(P_ind + P_dep), z, entries(R_ind + R_dep))
        return Estimates(m, P, np.zeros_like(P))

    @staticmethod
    def held(estimate: Estimates) -> Estimates:
        """Return an estimate the way this method holds it."""
        return Estimates(estimate.m, estimate.P_ind + estimate.P_dep,
                         np.zeros_like(estimate.P_dep))

    def absorb(self, landmarks: Ints, current: Estimates, index: Ints,
               rows: Rows) -> Optional[Estimates]:
        """
        Fuse accepted rows into their landmarks, each landmark's rows in order.

        ``landmarks`` (K,) the distinct rows of ``rows.rows``, ``current`` their
        estimates, ``index`` (N,) each row's index in them. Returns the new estimates
        of ``landmarks``, or None when they are left to ``settle``.
        """
        m, P_ind, P_dep = (x.copy() for x in current)
        rank = _ranks(index)
        for level in range(int(rank.max()) + 1 if len(rank) else 0):
            at = np.flatnonzero(rank == level)
            k = index[at]
            m[k], P_ind[k], P_dep[k] = self.fuse(m[k], P_ind[k], P_dep[k], rows.z[at],
                                                 rows.R_ind[at], rows.R_dep[at])
        return Estimates(m, P_ind, P_dep)

    def settle(self, rows: Ints) -> Tuple[Ints, Optional[Estimates]]:
        """Return the landmarks of ``rows`` left to fold and their estimates (none here)."""
        return rows[:0], None

    def start(self, row: int, cluster: Rows) -> Estimates:
        """Return a landmark's estimate from agreeing observations, fused in order."""
        m, P_ind, P_dep = cluster.z[:1], cluster.R_ind[:1], cluster.R_dep[:1]
        for k in range(1, len(cluster.rows)):
            m, P_ind, P_dep = self.fuse(m, P_ind, P_dep, cluster.z[k:k + 1],
                                        cluster.R_ind[k:k + 1], cluster.R_dep[k:k + 1])
        return self.held(Estimates(m, P_ind, P_dep))

    def replace(self, row: int, code: int, estimate: Estimates) -> None:
        """Note that a landmark's estimate (held, one row) was set from elsewhere."""

    def merge(self, keep: int, drop: int, kept: Estimates, dropped: Estimates) -> Estimates:
        """Return the estimate of ``keep`` with ``drop`` fused in (one row each)."""
        return self.held(self.fuse(*kept, *dropped))

    def retire(self, rows: Ints) -> None:
        """Forget the method state of landmarks taken out of the map (none)."""

    def records(self, row: int, names: Sequence[str]) -> Dict[str, Any]:
        """Return method state of one landmark for the saved map (none)."""
        return {}

    def load(self, row: int, record: Mapping[str, Any], estimate: Estimates,
             source_code: Callable[[str], int]) -> None:
        """Restore method state of one landmark from a saved record (none)."""

    def checkpoint(self, rows: Ints) -> Any:
        """Return what ``restore`` needs to undo an update of ``rows`` (nothing here)."""
        return None

    def restore(self, state: Any) -> None:
        """Undo an update from a ``checkpoint`` (nothing here)."""


class CovarianceIntersection(Independent):
    """Covariance intersection; the estimate is held as dependent (``P_ind = 0``)."""

    name = 'covariance_intersection'

    def fuse(self, m: NDArray[np.float64], P_ind: NDArray[np.float64],
             P_dep: NDArray[np.float64], z: NDArray[np.float64], R_ind: NDArray[np.float64],
             R_dep: NDArray[np.float64]) -> Estimates:
        """Fuse estimates with observations row by row (the closed form, omega optimal)."""
        P, R = P_ind + P_dep, R_ind + R_dep
        fused = ci_2x2(m, entries(P), z, entries(R))
        m, P = covariance_intersection(m, P, z, R) if fused is None else fused
        return Estimates(m, np.zeros_like(P), P)

    @staticmethod
    def held(estimate: Estimates) -> Estimates:
        """Return an estimate the way this method holds it."""
        return Estimates(estimate.m, np.zeros_like(estimate.P_ind),
                         estimate.P_ind + estimate.P_dep)


class SplitCovarianceIntersection(Independent):
    """
    Split CI across sources over per-(landmark, source) information sums.

    A landmark's estimate is the fold of its sums (``SourceSums``): ``absorb`` only
    adds to the sums and marks the landmark stale; ``settle`` folds the stale ones.
    """

    name = 'split_covariance_intersection'

    def reset(self) -> None:
        """Forget every landmark (the compiled fold starts loading at the first fold)."""
        self.sums = SourceSums(self.independent_sources)
        self.stale = np.zeros(64, bool)

    def _mark(self, rows, value):
        rows = np.asarray(rows, np.int64)
        if len(rows) and rows.max() >= len(self.stale):
            grown = np.zeros(max(int(rows.max()) + 1, 2 * len(self.stale)), bool)
            grown[:len(self.stale)] = self.stale
            self.stale = grown
        self.stale[rows] = value

    def fuse(self, m: NDArray[np.float64], P_ind: NDArray[np.float64],
             P_dep: NDArray[np.float64], z: NDArray[np.float64], R_ind: NDArray[np.float64],
             R_dep: NDArray[np.float64]) -> Estimates:
        """Fuse estimates with observations row by row (split CI, exact omega)."""
        return Estimates(*split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep))

    @staticmethod
    def held(estimate: Estimates) -> Estimates:
        """Return an estimate the way this method holds it (as it is)."""
        return estimate

    def absorb(self, landmarks: Ints, current: Estimates, index: Ints,
               rows: Rows) -> Optional[Estimates]:
        """Add accepted rows to their sums; their landmarks are left to ``settle``."""
        self.sums.add(rows.rows, rows.codes, rows.z, rows.R_ind, rows.R_dep)
        self._mark(landmarks, True)
        return None

    def settle(self, rows: Ints) -> Tuple[Ints, Optional[Estimates]]:
        """Fold the stale landmarks of ``rows``; return them and their estimates."""
        rows = np.asarray(rows, np.int64)
        rows = rows[rows < len(self.stale)]
        rows = rows[self.stale[rows]]
        self.stale[rows] = False
        return self.sums.fold_held(rows)

    def start(self, row: int, cluster: Rows) -> Estimates:
        """Replace a landmark's sums by those of agreeing observations; fold them."""
        self.sums.clear(np.array([row]))
        self.sums.add(cluster.rows, cluster.codes, cluster.z, cluster.R_ind, cluster.R_dep)
        self._mark([row], False)
        return self.sums.fold(np.array([row], np.int64))

    def replace(self, row: int, code: int, estimate: Estimates) -> None:
        """Collapse a landmark's sums into one source ``code`` holding ``estimate``."""
        self.sums.clear(np.array([row]))
        self.sums.add(np.array([row]), np.array([code]), *estimate)
        self._mark([row], False)

    def merge(self, keep: int, drop: int, kept: Estimates, dropped: Estimates) -> Estimates:
        """Add the sums of ``drop`` to those of ``keep``; return the fold of ``keep``."""
        self.sums.merge_into(keep, drop)
        self._mark([keep], False)
        return self.sums.fold(np.array([keep], np.int64))

    def retire(self, rows: Ints) -> None:
        """Forget the per-source sums of landmarks taken out of the map."""
        self.sums.clear(rows)
        self._mark(rows, False)

    def records(self, row: int, names: Sequence[str]) -> Dict[str, Any]:
        """Return the per-source sums of one landmark, sorted by source name."""
        return {'per_source': self.sums.records(row, names)}

    def load(self, row: int, record: Mapping[str, Any], estimate: Estimates,
             source_code: Callable[[str], int]) -> None:
        """Restore the per-source sums of one landmark (one source if absent)."""
        self.sums.load(row, record.get('per_source') or one_source(*estimate), source_code)
        self._mark([row], False)

    def checkpoint(self, rows: Ints) -> Any:
        """Return the sums of the pairs of ``rows`` (sorted) and the pairs."""
        return self.sums.checkpoint(), np.asarray(rows, np.int64)

    def restore(self, state: Any) -> None:
        """Put the sums back; the landmarks of the checkpoint are stale (fold again)."""
        sums, rows = state
        self.sums.restore(sums)
        self._mark(rows, True)


METHODS = {cls.name: cls for cls in (
    Independent, CovarianceIntersection, SplitCovarianceIntersection)}
"""The fusion methods by name."""

FUSION_METHODS = tuple(METHODS)
"""Their names."""

SOURCE_CORRELATIONS = ('unknown', 'independent')
"""``source_correlation`` values: the dependent parts of different sources correlated in
an unknown way (robots posed against a shared map), or independent (motion capture)."""


def make_method(fusion: str, source_correlation: str = 'unknown') -> Independent:
    """Return a new fusion method by name; ValueError for an unknown name or correlation."""
    if fusion not in METHODS:
        raise ValueError(f'fusion must be one of {tuple(METHODS)}, got {fusion!r}')
    if source_correlation not in SOURCE_CORRELATIONS:
        raise ValueError(f'source_correlation must be one of {SOURCE_CORRELATIONS}, '
                         f'got {source_correlation!r}')
    return METHODS[fusion](source_correlation == 'independent')
