"""
The update of sightings whose landmark is one of several (ROS-free).

A row without ID that fits several landmarks of the map (``localizer.association``,
``association_merge_ambiguous``) is applied as probabilistic data association
(Bar-Shalom and Fortmann, "Tracking and Data Association", 1988, ch. 6; detection
certain, no clutter): the rows whose landmark is known are applied first (one stacked
update, as always), then each ambiguous row once per candidate ``j``, from the same
state, giving ``x_j``, ``P_j``; the result is the moments of the mixture with the
association probabilities ``beta_j``:

    x = sum_j beta_j x_j,   P = sum_j beta_j (P_j + (x_j - x)(x_j - x)^T)

A candidate the row's gate rejects is dropped and the others renormalised; a row that
no candidate passes is not applied. Candidates close together give nearly one update;
candidates far apart leave the pose spread between them, never confident about a
pairing the data do not decide.
"""

from dataclasses import replace
import math
from typing import Callable, Optional, Tuple

from landmark_ros.localizer.steps import Batch
from landmark_ros.localizer.update import UpdateResult
import numpy as np
from numpy.typing import NDArray

UpdateRows = Callable[[NDArray[np.float64], NDArray[np.float64],
                       Optional[NDArray[np.float64]], Batch], Optional[UpdateResult]]
"""``(x, P, C, batch) -> UpdateResult`` (None when the update failed); ``C`` the
cross-covariance with the consider landmarks (``localizer.consider``) or None."""


def alternatives(merged, keep, map_index, m_map, P_map):
    """
    Return ``Batch.alternatives`` of the kept rows of a message (None without any).

    ``merged``: row -> (candidate IDs (C,), probabilities (C,)) (``label_rows``);
    ``keep`` (N,) bool: the rows that go into the batch; ``map_index``: ID -> index of
    ``m_map`` (K, 2), ``P_map`` (K, 2, 2).
    """
    if not merged:
        return None
    position = np.cumsum(keep) - 1
    out = {}
    for row, (cand_ids, beta) in merged.items():
        k = np.array([map_index[int(i)] for i in cand_ids], np.intp)
        out[int(position[row])] = (m_map[k], P_map[k], beta, np.asarray(cand_ids, np.int64))
    return out


def sub_batch(batch: Batch, rows: NDArray[np.intp]) -> Batch:
    """Return the rows ``rows`` of ``batch`` as a batch without alternatives."""

    def pick(a):
        return None if a is None else np.asarray(a)[rows]

    return replace(batch, m=batch.m[rows], P_m=batch.P_m[rows], z=batch.z[rows],
                   R=batch.R[rows], kind=batch.kind[rows], shared=pick(batch.shared),
                   shared_bias=pick(batch.shared_bias), landmarks=pick(batch.landmarks),
                   result=None, alternatives=None)


def collapse(x_parts, P_parts, beta) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """
    Return the mean and covariance of a Gaussian mixture (the heading wrapped).

    ``x_parts`` (C, n), ``P_parts`` (C, n, n), ``beta`` (C,) summing to 1. The heading
    (component 2) is averaged as its offsets from the first part's, wrapped.
    """
    x_parts = np.array(x_parts, dtype=np.float64)
    ref = x_parts[0, 2]
    x_parts[:, 2] = ref + (x_parts[:, 2] - ref + math.pi) % (2.0 * math.pi) - math.pi
    x = beta @ x_parts
    d = x_parts - x
    P = np.einsum('c,cij->ij', beta, P_parts) + np.einsum('c,ci,cj->ij', beta, d, d)
    x[2] = (x[2] + math.pi) % (2.0 * math.pi) - math.pi
    return x, 0.5 * (P + P.T)


def update_mixture(x: NDArray[np.float64], P: NDArray[np.float64],
                   C: Optional[NDArray[np.float64]], batch: Batch,
                   update_rows: UpdateRows) -> UpdateResult:
    """
    Apply ``batch``: its known rows, then each row of ``batch.alternatives`` by PDA.

    Returns an ``UpdateResult`` with the state, its covariance, the cross-covariance
    with the consider landmarks (the candidates' weighted sum: the landmarks' means are
    the same in every candidate) and, over the batch's rows for the counters, an
    ambiguous row used when a candidate passed its gate, gated when none did; NIS and
    weight of the known rows' update.
    """
    n = len(batch.z)
    ambiguous = sorted(batch.alternatives or {})
    known = np.setdiff1d(np.arange(n), ambiguous)
    used, gated = np.zeros(n, bool), np.zeros(n, bool)
    first = UpdateResult(x, P, used, gated, math.nan, 0, 1.0, 0)
    if len(known):
        result = update_rows(x, P, C, sub_batch(batch, known))
        if result is not None:
            x, P, C, first = result.x, result.P, result.C, result
            used[known], gated[known] = result.used, result.gated
    for row in ambiguous:
        m_c, P_c, beta, ids = batch.alternatives[row]
        one = sub_batch(batch, np.array([row]))
        parts = [update_rows(x, P, C, replace(one, m=m_c[j:j + 1], P_m=P_c[j:j + 1],
                                              landmarks=ids[j:j + 1]))
                 for j in range(len(beta))]
        ok = [j for j, r in enumerate(parts) if r is not None and r.used[0]]
        gated[row] = not ok
        if not ok:
            continue
        used[row] = True
        w = np.asarray(beta, dtype=np.float64)[ok]
        w = w / w.sum()
        x, P = collapse([parts[j].x for j in ok], np.array([parts[j].P for j in ok]), w)
        C = _collapse_cross([parts[j].C for j in ok], w)
    return UpdateResult(x, P, used, gated, first.nis, first.dof, first.omega,
                        first.iterations, None, C)


def _collapse_cross(parts, w):
    """Return the weighted sum of the candidates' ``C`` (None when they have none)."""
    if parts[0] is None:
        return None
    width = max(c.shape[1] for c in parts)
    return sum(wj * np.pad(c, ((0, 0), (0, width - c.shape[1]))) for wj, c in zip(w, parts))
