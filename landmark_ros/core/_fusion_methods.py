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
from landmark_ros.core._arrays import mahalanobis_sq_2x2
from landmark_ros.core._source_sums import _entries, _one_source, _rank, _SourceParts, _terms
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

    def prepare(self, landmark_map, rows, batch, positions, result, changed):
        """
        Get ready for the rows of confirmed landmarks of a batch (nothing here).

        Returns True when it fused them itself (the rounds are then skipped).
        """
        return False

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
        self.planned = None

    _PLAN_PASSES = 8
    """Most passes of ``prepare`` (each rules out one more rejected row per landmark)."""

    def prepare(self, landmark_map, rows, batch, positions, result, changed):
        """
        Find the estimates after each row of confirmed landmarks of a batch at once.

        ``rows`` (landmark rows, in arrival order) at ``positions`` in the batch. The
        rows are gated here as ``LandmarkMap`` will gate them (same numbers, same
        decisions): a first pass takes every row as accepted; each further pass, for
        the landmarks that had one, leaves out the first row that failed its gate and
        folds their rows again. ``update`` then takes these estimates while the map's
        decisions match (a reinitialisation in between breaks the landmark) and folds
        the others itself. Only worth it when some landmark has several rows.
        """
        self.planned = None
        if _fold_kernel.load() is not None:
            run = self.parts.run(landmark_map, rows, batch, positions)
            if landmark_map._apply_run(rows, batch, positions, run, result, changed):
                self.parts.commit(run)
                return True
            self.parts.rollback(run)
            self.planned = self.parts.planned(run, len(batch.codes), positions)
            return False
        if len(rows) < 2 or len(np.unique(rows)) == len(rows):
            return False
        count = len(rows)
        codes = batch.codes[positions]
        z, R_ind, R_dep = batch.z[positions], batch.R_ind[positions], batch.R_dep[positions]
        terms = np.concatenate(_terms(z, R_ind, R_dep), axis=1)
        landmarks, landmark = np.unique(rows, return_inverse=True)
        landmark = landmark.reshape(-1)
        # Rows by landmark, in arrival order within each: the previous included row.
        order = np.argsort(landmark, kind='stable')
        start = np.searchsorted(landmark[order], landmark[order])
        include = np.ones(count, bool)
        planned = np.ones(count, bool)
        m, P_ind, P_dep = np.zeros((count, 2)), np.zeros((count, 2, 2)), np.zeros((count, 2, 2))
        todo = np.arange(count)
        for _ in range(self._PLAN_PASSES):
            states = self.parts.plan(rows[todo], codes[todo], terms[todo], include[todo])
            if states is None:
                return False
            m[todo], P_ind[todo], P_dep[todo] = states
            # Each row against the state before it (the map's for a landmark's first).
            held = np.where(include[order], np.arange(count), -1)
            previous = np.full(count, -1)
            previous[1:] = np.maximum.accumulate(held)[:-1]
            previous = np.where(previous >= start, previous, -1)
            before = np.full(count, -1)
            before[order] = np.where(previous >= 0, order[np.maximum(previous, 0)], -1)
            first = before < 0
            mean, cov_ind, cov_dep = m[before], P_ind[before], P_dep[before]
            mean[first] = landmark_map.mean[rows[first]]
            cov_ind[first] = landmark_map.cov_ind[rows[first]]
            cov_dep[first] = landmark_map.cov_dep[rows[first]]
            S = cov_ind + cov_dep + R_ind + R_dep
            d = z - mean
            d2 = mahalanobis_sq_2x2(d[:, 0], d[:, 1], *_entries(S))
            failed = include & ~(d2 <= landmark_map.threshold)
            if not failed.any():
                break
            # The first failing row of each landmark is rejected for sure.
            first_failed = np.full(len(landmarks), count)
            np.minimum.at(first_failed, landmark[failed], _rank(landmark)[failed])
            hit = first_failed[landmark] == _rank(landmark)
            include[hit] = False
            again = np.zeros(len(landmarks), bool)
            again[landmark[hit]] = True
            todo = np.flatnonzero(again[landmark])
        else:
            planned[todo] = False
        size = len(batch.codes)
        at = np.full(size, -1, np.int64)
        at[positions[planned]] = np.flatnonzero(planned)
        included = np.cumsum(include[order]) - include[order]
        accepted_before = np.empty(count, np.int64)
        accepted_before[order] = included - included[start]
        self.planned = {'m': m, 'P_ind': P_ind, 'P_dep': P_dep, 'at': at,
                        'landmarks': landmarks, 'landmark': landmark,
                        'accepted_before': accepted_before,
                        'accepted': np.zeros(len(landmarks), np.int64),
                        'broken': np.zeros(len(landmarks), bool)}

    def finish(self):
        """Forget what ``prepare`` found; the update is over."""
        self.planned = None
        self.parts.finish()

    def fuse(self, m, P_ind, P_dep, z, R_ind, R_dep):
        """Fuse estimates with observations row by row (split CI, exact omega)."""
        return split_covariance_intersection(m, P_ind, P_dep, z, R_ind, R_dep)

    def update(self, landmark_map, rows, codes, z, R_ind, R_dep, positions=None):
        """
        Add accepted observations (one per landmark) to their sums; refold those rows.

        A row whose landmark had every earlier row of the batch accepted takes the
        estimate ``prepare`` found (the same, bit for bit); the others are folded here.
        """
        self.parts.add(rows, codes, z, R_ind, R_dep, unique=True)
        plan = self.planned
        if plan is None or positions is None:
            return self.parts.combine(rows)
        at = plan['at'][positions]
        ready = at >= 0
        landmark = plan['landmark'][np.maximum(at, 0)]
        ready &= ~plan['broken'][landmark] & (
            plan['accepted'][landmark] == plan['accepted_before'][np.maximum(at, 0)])
        plan['accepted'][landmark[ready]] += 1
        at = at[ready]
        if ready.all():
            return plan['m'][at], plan['P_ind'][at], plan['P_dep'][at]
        m, P_ind, P_dep = np.empty((len(rows), 2)), np.empty((len(rows), 2, 2)), np.empty(
            (len(rows), 2, 2))
        m[ready], P_ind[ready], P_dep[ready] = plan['m'][at], plan['P_ind'][at], plan[
            'P_dep'][at]
        rest = ~ready
        m[rest], P_ind[rest], P_dep[rest] = self.parts.combine(rows[rest])
        return m, P_ind, P_dep

    def initialise(self, landmark_map, row, cluster):
        """Replace a landmark's sums by those of agreeing observations; fold them."""
        if self.planned is not None:     # what prepare found for it no longer holds
            plan = self.planned
            at = np.searchsorted(plan['landmarks'], row)
            if at < len(plan['landmarks']) and plan['landmarks'][at] == row:
                plan['broken'][at] = True
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
