"""
The fusion methods of ``LandmarkMap``: one small strategy object per method.

Each has ``fuse`` (estimates with observations, row by row), ``update`` (the new
estimates of landmarks with one accepted observation each), ``initialise`` (a
landmark from agreeing observations), ``held`` (an estimate the way the method
holds it: as independent, dependent, or split), ``records`` / ``load`` (method state
in the saved map), ``checkpoint`` / ``restore`` (undo of a failed update) and
``prepare`` / ``finish`` (a batch's confirmed rows at once, where the method can).
Private to ``core``: ``landmark_map`` is the interface, and its module docstring
says what each method assumes.

Sources: the product of Gaussians, the textbook chapter; covariance intersection,
Julier and Uhlmann, "A non-divergent estimation algorithm in the presence of unknown
correlations", ACC 1997; split covariance intersection, Julier and Uhlmann, "General
decentralized data fusion with covariance intersection", Handbook of Multisensor Data
Fusion, 2001.
"""

from landmark_ros.core import _fold_kernel
from landmark_ros.core._source_sums import _entries, _one_source, _SourceParts
from landmark_ros.core.gaussian import (ci_2x2, covariance_intersection, fuse_2x2,
                                        split_covariance_intersection)
import numpy as np


def _stack(observations):
    """Return ``z, R_ind, R_dep`` of a list of observations as arrays."""
    return (np.array([obs.z for obs in observations]),
            np.array([obs.R_ind for obs in observations]),
            np.array([obs.R_dep for obs in observations]))


class _Independent:
    """Product of Gaussians; the estimate is held as independent (``P_dep = 0``)."""

    name = 'independent'

    def reset(self):
        """Forget every landmark (nothing to forget)."""

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row; return ``(m, P_ind, P_dep)``."""
        # The closed form behind gaussian.fuse, on entries (batches of (N, 2) here).
        m, P = fuse_2x2(m, _entries(P_ind + P_dep), z, _entries(R_ind + R_dep))
        return m, P, np.zeros_like(P)

    def prepare(self, landmark_map, rows, batch, positions, result, changed, lazy=False):
        """
        Fuse what it can of the rows of confirmed landmarks of a batch (nothing here).

        Returns the indices into ``rows`` it left to the rounds (here all of them).
        """
        return np.arange(len(rows))

    def settle(self, rows):
        """Return the landmarks of ``rows`` left to fold, and their estimates (none here)."""
        return np.empty(0, np.int64), np.empty((0, 8))

    def finish(self):
        """Forget what ``prepare`` found (nothing here)."""

    def update(self, landmark_map, rows, codes, z, R_ind, R_dep, positions=None):
        """Return the new estimates of ``rows`` (one accepted observation each)."""
        return self.fuse(landmark_map.mean[rows], landmark_map.cov_ind[rows],
                         landmark_map.cov_dep[rows], z, R_ind, R_dep)

    def initialise(self, landmark_map, row, cluster):
        """Return the estimate of a landmark from agreeing observations, in order."""
        z, R_ind, R_dep = _stack(cluster)
        m, P_ind, P_dep = z[:1], R_ind[:1], R_dep[:1]
        for k in range(1, len(cluster)):
            m, P_ind, P_dep = self.fuse(m, P_ind, P_dep, z[k:k + 1], R_ind[k:k + 1],
                                        R_dep[k:k + 1])
        return self.held(m[0], P_ind[0], P_dep[0])

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, P_ind + P_dep, np.zeros_like(P_dep)

    def records(self, landmark_map, row):
        """Return method state of one landmark for ``to_records`` (none)."""
        return {}

    def checkpoint(self, rows):
        """Return what ``restore`` needs to undo an update of ``rows`` (nothing here)."""
        return None

    def restore(self, state):
        """Undo an update from a ``checkpoint`` (nothing here)."""

    def load(self, landmark_map, row, record, m, P_ind, P_dep):
        """Restore method state of one landmark (none)."""

    def retire(self, rows):
        """Forget the method state of landmarks taken out of the map (none)."""


class _CovarianceIntersection(_Independent):
    """Covariance intersection; the estimate is held as dependent (``P_ind = 0``)."""

    name = 'covariance_intersection'

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row; return ``(m, P_ind, P_dep)``."""
        P, R = P_ind + P_dep, R_ind + R_dep
        fused = ci_2x2(m, _entries(P), z, _entries(R))   # the closed form, omega optimal
        m, P = covariance_intersection(m, P, z, R) if fused is None else fused
        return m, np.zeros_like(P), P

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, np.zeros_like(P_ind), P_ind + P_dep


class _SplitCovarianceIntersection(_Independent):
    """Split CI across sources over per-(landmark, source) information sums."""

    name = 'split_covariance_intersection'

    def reset(self):
        """Forget every landmark."""
        self.parts = _SourceParts()

    def prepare(self, landmark_map, rows, batch, positions, result, changed, lazy=False):
        """
        Gate and fold the rows of confirmed landmarks of a batch in the compiled kernel.

        ``rows`` (landmark rows, in arrival order) at ``positions`` in the batch, gated
        as ``LandmarkMap``'s rounds would gate them (same numbers, same decisions),
        each landmark folded at its gate refreshes and once after its last row (with
        ``lazy``: when ``settle`` asks). The map takes the outcome of every landmark
        that the batch does not rebuild (``max_consecutive_rejections`` in a row); the
        rows of those it does are undone here and left to the rounds, as are all rows
        without numba. Returns the indices into ``rows`` left to the rounds.
        """
        if _fold_kernel.load() is None:
            return np.arange(len(rows))
        run = self.parts.run(landmark_map, rows, batch, positions, lazy)
        rebuilt, streak = landmark_map._rebuilt_in(run)
        left = np.flatnonzero(rebuilt[run['landmark']])
        if rebuilt.any():
            self.parts.rollback(run, rebuilt)
            if rebuilt.all():
                return left
            run, kept = _SourceParts.without(run, rebuilt)
            rows, positions, streak = rows[kept], positions[kept], None
        landmark_map._apply_run(rows, batch, positions, run, result, changed, streak)
        self.parts.commit(run)
        return left

    def finish(self):
        """Stop journaling changes of the sums: the update is over."""
        self.parts.finish()

    def settle(self, rows):
        """Fold the landmarks of ``rows`` that a lazy batch left; return them, their states."""
        return self.parts.settle(rows)

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row (split CI, exact omega)."""
        return split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep)

    def update(self, landmark_map, rows, codes, z, R_ind, R_dep, positions=None):
        """Add accepted observations (one per landmark) to their sums; refold those rows."""
        self.parts.add(rows, codes, z, R_ind, R_dep, unique=True)
        return self.parts.combine(rows)

    def initialise(self, landmark_map, row, cluster):
        """Replace a landmark's sums by those of agreeing observations; fold them."""
        z, R_ind, R_dep = _stack(cluster)
        codes = np.array([landmark_map.source_code(obs.source) for obs in cluster], np.int64)
        self.parts.clear(row)
        self.parts.add(np.full(len(cluster), row, np.int64), codes, z, R_ind, R_dep)
        m, P_ind, P_dep = self.parts.combine(np.array([row], np.int64))
        return m[0], P_ind[0], P_dep[0]

    @staticmethod
    def held(m, P_ind, P_dep):
        """Return an estimate the way this method holds it."""
        return m, P_ind, P_dep

    def records(self, landmark_map, row):
        """Return the per-source sums of one landmark, sorted by source name."""
        return {'per_source': self.parts.records(row, landmark_map.source_names)}

    def load(self, landmark_map, row, record, m, P_ind, P_dep):
        """Restore the per-source sums of one landmark (one source if absent)."""
        self.parts.load(row, record.get('per_source') or _one_source(m, P_ind, P_dep),
                        landmark_map.source_code)

    def checkpoint(self, rows):
        """Return the pair index and the sums of the pairs of ``rows``."""
        return self.parts.checkpoint(rows)

    def restore(self, state):
        """Put the pair index and the saved sums back."""
        self.parts.restore(state)

    def retire(self, rows):
        """Forget the per-source sums of landmarks taken out of the map."""
        for row in np.asarray(rows).tolist():
            self.parts.clear(row)


_STRATEGIES = {cls.name: cls for cls in (
    _Independent, _CovarianceIntersection, _SplitCovarianceIntersection)}
