"""
A moved landmark, found from its innovation sequence by Page's CUSUM test (ROS-free).

Symbols: ``d2`` the normalised innovation squared (NIS) of an observation of a confirmed
landmark, ``d^T S^-1 d`` with ``d`` its innovation and ``S`` the innovation covariance
of the detector's reference filter (``fuser.change_reference``, see below);
``lambda`` a noncentrality; ``h`` the test's threshold; ``alpha`` the false-alarm rate
per observation of a static landmark.

The test
--------
While a landmark stays where it is, ``d2`` is chi-square with 2 degrees of freedom (H0).
Once it has moved by ``delta``, ``d`` has mean ``delta`` and ``d2`` is noncentral
chi-square, noncentrality ``lambda = delta^T S^-1 delta`` (H1). The density of the
latter is ``f_lambda(x) = exp(-(x + lambda) / 2) I0(sqrt(lambda x)) / 2``, so the
log-likelihood ratio of one observation is

    g(x) = log(f_lambda1(x) / f_0(x)) = log I0(sqrt(lambda1 x)) - lambda1 / 2

and Page's test (E. S. Page, "Continuous inspection schemes", Biometrika 41, 1954)
accumulates it: ``C_k = max(0, C_{k-1} + g(min(d2_k, clip)))``, an alarm when
``C_k > h``. ``lambda1 = shift_sigma ** 2``: the test is tuned to a move of
``shift_sigma`` standard deviations of one observation (the direction does not matter;
``g`` is the optimal increment for that size). ``d2`` is clipped at the gate's
threshold, so one wild row adds at most ``g(clip)`` (about 3 for the defaults) and cannot
raise an alarm alone; the clip is part of the run-length computation below. There is one
test per landmark over the whole team (every source's rows, in arrival order): a move is
seen by every source, and the rows of all of them shorten the delay.

Sources
-------
A source's own persistent error (a robot whose camera misreads one landmark for a few
seconds) shifts that source's rows only; a move shifts every source's. With
``min_sources`` ``m`` > 1 the statistic is the evidence of each source since the run
began, each counted up to ``h / m``: ``C_k = sum_s min(G_s, h / m)``, ``G_s`` the sum
of ``g`` over source ``s``'s rows since ``C`` last was 0; the run restarts when ``C``
falls to 0 and an alarm needs ``C >= h``, so at least ``m`` sources each with ``h / m``
of their own. ``m = 1`` is Page's test. The cap only lowers the statistic: from any
restart it stays at or below Page's statistic started at the same row, so its run
lengths are at least Page's and the false-alarm rate at most ``alpha`` (the
threshold below is Page's). The price is a longer delay: the Monte Carlo
(``eval.moved_landmark``, three robots) detects a 2-sigma move within 20 rows as often
as ``m = 1`` (98 %), with a median delay of 8 rows instead of 7; a landmark that only
one source sees is never rebuilt by this test (``max_consecutive_rejections`` still
rebuilds it after a large move).

Threshold from the false-alarm rate
-----------------------------------
After an alarm the test restarts, so the long-run rate of false alarms per observation of a
static landmark is ``1 / ARL0``, the average run length under H0 (renewal theorem). ``h``
is the threshold whose ARL0 is ``1 / alpha``, found by bisection on the ARL computed with
Brook and Evans' Markov chain (D. Brook and D. A. Evans, "An approach to the probability
distribution of cusum run length", Biometrika 59, 1972): ``C`` on ``[0, h]`` in
``STATES`` cells plus the atom at 0, the transition probabilities from the distribution
of ``g(min(d2, clip))`` (``d2`` chi-square, ``P(d2 <= x) = 1 - exp(-x / 2)``), and
``ARL = (I - Q)^-1 1`` from the atom. The same chain with the noncentral distribution
gives the mean delay to detection (``average_run_length(..., lambda_true)``). With
``alpha`` 2e-5 (``config/mrclam.yaml``), ``shift_sigma`` 1.75 and gate 0.999 ``h`` is 8.71 and a
2-sigma move (``lambda`` 4) takes 10.5 observations on average from ``C = 0``
(``lambda`` 3: 15.1). ``shift_sigma`` a little under 2 detects a 2-sigma move within
20 observations more often at the same false-alarm rate than 2 or more (simulated:
``lambda1`` 3, 4, 5, 6: 97.8, 96.6, 95.2, 93.1 % at about 0.25 false alarms per
10,000 observations, without the clip).

The ARL assumes independent innovations with the covariance they are normalised by.
The ``d2`` are therefore those of the detector's reference filter
(``fuser.change_reference``), not of the map: the Kalman filter of the rows' own model
(time-correlated noise per source when ``noise_correlation_time_s`` is set), whose
innovations are independent with their exact covariance whatever the fusion method
(CI and split CI inflate the map's covariance, which would hide a move). Errors the
model does not hold raise the false-alarm rate. ``python -m
landmark_ros.eval.moved_landmark`` measures detection and false alarms.

Change point and rebuild
------------------------
Page's estimate of where the change began is just after the last observation with
``C = 0``: the rows since (the post-change rows, at most ``MAX_POST_CHANGE_ROWS``, the
most recent), taken at the alarm from the ring of recent rows (``fuser.change_rows``;
rows older than the ring are gone). On an alarm the landmark is rebuilt from them
alone (``LandmarkMap.rebuild``: their largest agreeing subset, at least
``min_observations``), by the map's fusion method (split CI: its per-source sums start
again from those rows). The test restarts at 0 whether or not the rebuild took place.
The detector's state is not saved with the map: after a restart a test starts at 0,
which only delays a detection.
"""

from collections import Counter
from functools import lru_cache
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

from landmark_ros.core.arrays import unique_inverse
from landmark_ros.fuser.change_reference import NoiseModel, ReferenceFilter
from landmark_ros.fuser.change_rows import Groups, RowLog, subset
from landmark_ros.fusion import compiled
from landmark_ros.fusion.records import Observation, UpdateResult
import numpy as np
from numpy.typing import NDArray
from scipy import optimize, special, stats

STATES = 200
"""Cells of Brook and Evans' Markov chain on [0, h] (for the defaults the ARL differs by
0.1 % from that of 800 cells)."""

MAX_POST_CHANGE_ROWS = 64
"""Post-change rows kept per landmark (the most recent) for the rebuild."""


def increment(d2: NDArray[np.float64], noncentrality: float) -> NDArray[np.float64]:
    """
    Return Page's increment ``g(d2) = log I0(sqrt(lambda1 d2)) - lambda1 / 2``.

    Parameters
    ----------
    d2 : ndarray, shape (N,)
        Normalised innovations squared (not negative, finite).
    noncentrality : float
        ``lambda1``, the noncentrality of the move the test is tuned to (> 0).

    Returns
    -------
    ndarray, shape (N,)
        The log-likelihood ratios (``i0e`` keeps them finite for any ``d2``).

    """
    s = np.sqrt(noncentrality * np.asarray(d2, np.float64))
    return np.log(special.i0e(s)) + s - 0.5 * noncentrality


def _increment_cdf(y, noncentrality, clip, d2_cdf):
    """Return ``P(g(min(d2, clip)) <= y)`` for the ``d2`` distribution ``d2_cdf``."""
    grid = np.linspace(0.0, clip, 4001)
    values = increment(grid, noncentrality)
    x = np.interp(y, values, grid)       # g is increasing: its inverse on the grid
    return np.where(y >= values[-1], 1.0, np.where(y < values[0], 0.0, d2_cdf(x)))


def average_run_length(threshold: float, noncentrality: float, clip: float,
                       true_noncentrality: float = 0.0) -> float:
    """
    Return the average run length of Page's test to its first alarm (Brook and Evans).

    Parameters
    ----------
    threshold : float
        ``h`` (> 0).
    noncentrality : float
        ``lambda1``, what the test is tuned to.
    clip : float
        ``d2`` is clipped at this value (> 0).
    true_noncentrality : float
        The noncentrality of the observations: 0 for a static landmark (ARL0, the mean
        number of observations to a false alarm), else the mean delay to detection of a
        move of that size.

    Returns
    -------
    float
        Observations, counted from ``C = 0``.

    """
    if true_noncentrality > 0.0:
        def d2_cdf(x):
            return stats.ncx2.cdf(x, 2, true_noncentrality)
    else:
        def d2_cdf(x):
            return -np.expm1(-0.5 * x)
    width = threshold / STATES
    levels = np.concatenate([[0.0], (np.arange(1, STATES + 1) - 0.5) * width])
    edges = np.arange(STATES + 1) * width           # cell j is (edges[j-1], edges[j]]
    cdf = _increment_cdf(edges[None, :] - levels[:, None], noncentrality, clip, d2_cdf)
    Q = np.empty((STATES + 1, STATES + 1))
    Q[:, 0] = cdf[:, 0]
    Q[:, 1:] = np.diff(cdf, axis=1)
    run = np.linalg.solve(np.eye(STATES + 1) - Q, np.ones(STATES + 1))
    return float(run[0])


@lru_cache(maxsize=32)
def threshold_for(false_alarm_rate: float, noncentrality: float, clip: float) -> float:
    """
    Return ``h`` whose ARL0 is ``1 / false_alarm_rate`` (bisection on the ARL).

    Parameters
    ----------
    false_alarm_rate : float
        False alarms per observation of a static landmark, in [1e-12, 0.5).
    noncentrality : float
        ``lambda1``.
    clip : float
        The clip of ``d2``.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        If ``false_alarm_rate`` is out of range.

    """
    if not 1e-12 <= false_alarm_rate < 0.5:
        raise ValueError(f'false_alarm_rate must be in (0, 0.5), got {false_alarm_rate}')
    target = -np.log(false_alarm_rate)

    def gap(h):
        return np.log(average_run_length(h, noncentrality, clip)) - target
    return float(optimize.brentq(gap, 1e-3, _highest_threshold(noncentrality, clip), xtol=1e-6))


def _highest_threshold(noncentrality, clip):
    """Return an ``h`` whose ARL0 is above 1e12 (the bisection's upper end)."""
    h = 4.0
    while average_run_length(h, noncentrality, clip) < 1e12:
        h *= 1.5
    return h


class PostChange(NamedTuple):
    """A landmark whose test raised an alarm, with its post-change rows."""

    landmark_id: int
    observations: List[Observation]


class MoveDetector:
    """
    Page's test per confirmed landmark over the team's NIS sequence (module notes).

    Parameters
    ----------
    false_alarm_rate : float
        False alarms per observation of a static landmark, in [1e-12, 0.5).
    shift_sigma : float
        The move the test is tuned to, in standard deviations of one observation (> 0).
    clip : float
        ``d2`` is clipped here (the gate's chi-square threshold).
    noise : NoiseModel
        The rows' time correlation (``fuser.change_reference``); white by default.
    min_sources : int
        Sources an alarm needs (>= 1): each one's evidence counts up to ``h / min_sources``.

    Raises
    ------
    ValueError
        If ``false_alarm_rate`` or ``min_sources`` is out of range.

    """

    def __init__(self, false_alarm_rate: float, shift_sigma: float, clip: float,
                 noise: NoiseModel = NoiseModel(), min_sources: int = 1) -> None:
        if int(min_sources) < 1:
            raise ValueError(f'min_sources must be at least 1, got {min_sources}')
        self.reference = ReferenceFilter(noise, clip)
        """The filters whose innovations the tests take."""
        self.noncentrality = float(shift_sigma) ** 2
        self.clip = float(clip)
        self.threshold = threshold_for(float(false_alarm_rate), self.noncentrality, self.clip)
        self.cap = self.threshold / int(min_sources) if int(min_sources) > 1 else np.inf
        """The most evidence one source's rows count for in a landmark's statistic (none
        for ``min_sources`` 1: Page's test on the team's rows)."""
        self.alarms: Counter[int] = Counter()
        """Alarms raised per landmark ID (whether or not the rebuild took place)."""
        self.tested = 0
        """Rows the tests took (the denominator of the false-alarm rate)."""
        self._slots: Dict[int, int] = {}
        self._ids = np.zeros(0, np.int64)            # landmark ID per slot
        self._names: List[str] = []
        self._codes: Dict[str, int] = {}
        self._C = np.zeros(0)                       # statistic per slot
        self._E = np.zeros((0, 0))                  # evidence per slot and source
        self._first = np.zeros(0, np.int64)         # sequence number where the run began
        self._log = RowLog()

    @property
    def statistic(self) -> Dict[int, float]:
        """``C`` of each landmark whose test is above 0."""
        return {i: float(self._C[s]) for i, s in self._slots.items() if self._C[s] > 0.0}

    def reset(self, ids: Optional[Sequence[int]] = None) -> None:
        """Restart the tests of ``ids`` (all when None) at 0, and their filters."""
        if ids is None:
            self.reference.clear()
        else:
            self.reference.reset(ids)
        slots = [self._slots[int(i)] for i in (self._slots if ids is None else ids)
                 if int(i) in self._slots]
        self._restart(np.array(slots, np.int64))

    def _restart(self, slots: NDArray[np.int64]) -> None:
        """Put tests back at 0: no evidence, the run begins with the next row."""
        self._C[slots] = 0.0
        self._E[slots] = 0.0
        self._first[slots] = self._log.next

    def observe(self, ids: NDArray[np.int64], d2: NDArray[np.float64],
                rows: Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                            NDArray[Any], NDArray[np.int64]],
                names: Optional[Sequence[str]] = None,
                groups: Optional[Tuple[NDArray[np.int64], NDArray[np.intp]]] = None
                ) -> List[PostChange]:
        """
        Add rows (in arrival order) to their landmarks' tests; return the alarms.

        Parameters
        ----------
        ids : ndarray of int, shape (N,)
            Landmark IDs.
        d2 : ndarray, shape (N,)
            Their NIS; NaN for rows the test does not take (landmarks not confirmed).
        rows : tuple
            ``z`` (N, 2) [m], ``R_ind``, ``R_dep`` (N, 2, 2) [m^2], the source names (N,)
            and stamps (N,) [ns] of the rows (for the rebuild).
        names : sequence of str, optional
            The sources' names; when given, ``rows``' source column holds indices into it
            (int, (N,)) instead of names.
        groups : tuple, optional
            ``core.arrays.unique_inverse(ids)``, when the caller has it.

        Returns
        -------
        list of PostChange
            The landmarks whose test raised an alarm (restarted at 0 after the batch:
            one alarm per landmark and batch), each with its post-change rows in arrival
            order, the batch's rows after the alarm included (they are fused already).

        """
        mask = np.isfinite(d2)
        taken = np.flatnonzero(mask)
        self.tested += len(taken)
        if not len(taken):
            return []
        g = increment(np.minimum(d2[taken], self.clip), self.noncentrality)
        if names is None:
            unique, inverse = np.unique(np.asarray(rows[3])[taken].astype(str),
                                        return_inverse=True)
            names = unique.tolist()
        else:
            inverse = np.asarray(rows[3])[taken]
        codes = np.array([self._code(str(name)) for name in names], np.int64)[inverse]
        landmarks = ids[taken].astype(np.int64)
        sequence = self._log.append(landmarks, codes, taken, rows)
        slots = self._slots_of(unique_inverse(landmarks) if groups is None else
                               subset(groups, mask))
        alarm = compiled.cusum((self._E, self._C, self._first), (slots, codes, g, sequence),
                               self.threshold * (1.0 - 1e-12), self.cap)
        if alarm is not None:
            alarms = self._raise(slots[alarm])
        else:
            looped = self._fast(slots, codes, g, sequence)
            alarms = self._loop(slots[looped], codes[looped], g[looped], sequence[looped])
        return [PostChange(landmark_id, self._log.rows_of(
            landmark_id, first, self._names, MAX_POST_CHANGE_ROWS))
            for landmark_id, first in alarms]

    def _code(self, name: str) -> int:
        """Return a source's column in the evidence (a new one when it is new)."""
        if name not in self._codes:
            self._codes[name] = len(self._names)
            self._names.append(name)
            self._E = np.pad(self._E, ((0, 0), (0, 1)))
        return self._codes[name]

    def _slots_of(self, groups: Tuple[NDArray[np.int64], NDArray[np.intp]]) -> NDArray[np.int64]:
        """
        Return the state rows of rows' landmarks, given ``unique_inverse`` of their IDs.

        New landmarks get new, restarted rows.
        """
        unique, inverse = groups
        fresh = [i for i in unique.tolist() if i not in self._slots]
        if fresh:
            start = len(self._C)
            self._slots.update(zip(fresh, range(start, start + len(fresh))))
            self._ids = np.concatenate([self._ids, np.array(fresh, np.int64)])
            self._C = np.concatenate([self._C, np.zeros(len(fresh))])
            self._E = np.concatenate([self._E, np.zeros((len(fresh), self._E.shape[1]))])
            self._first = np.concatenate([self._first, np.full(len(fresh), self._log.next)])
        return np.array([self._slots[i] for i in unique.tolist()], np.int64)[inverse]

    def _fast(self, slots, codes, g, sequence):
        """
        Settle the landmarks whose sources all stay under the cap and raise no alarm.

        For them the statistic is Page's (the sum of the evidence), in closed form per
        landmark (Lindley's recursion). Return the mask of the rows left to ``_loop``.
        """
        batch = Groups(slots)
        K = self._E.shape[1]
        key = batch.group * K + codes[batch.order]
        g, sequence = g[batch.order], sequence[batch.order]
        E0 = self._E[batch.unique]
        slow = (E0 > self.cap).any(axis=1)
        if np.isfinite(self.cap):       # the most a source's evidence reaches in the batch
            pairs = Groups(key)
            peak = np.maximum.reduceat(pairs.lindley(
                g[pairs.order], np.maximum(E0.ravel()[pairs.unique], 0.0)), pairs.starts)
            slow |= np.bincount(pairs.unique // K, peak > self.cap, batch.count) > 0
        statistic = batch.lindley(g, self._C[batch.unique])
        slow |= np.maximum.reduceat(statistic, batch.starts) >= self.threshold * (1.0 - 1e-12)
        zero = np.where(statistic <= 0.0, np.arange(len(g)), -1)
        last_zero = np.maximum.accumulate(zero)[batch.ends]
        restarted = last_zero >= batch.starts
        in_run = np.arange(len(g)) >= np.where(restarted, last_zero + 1,
                                               batch.starts)[batch.group]
        E = np.bincount(key, g * in_run, batch.count * K).reshape(-1, K)
        E += np.where(restarted[:, None], 0.0, E0)
        fast = ~slow
        rows = batch.unique[fast]
        begun = (restarted | (self._C[batch.unique] <= 0.0))[fast]    # a run began here
        first = np.where(restarted, sequence[np.minimum(last_zero + 1, batch.ends)],
                         sequence[batch.starts])[fast]
        self._first[rows] = np.where(begun, first, self._first[rows])
        self._E[rows] = E[fast]
        self._C[rows] = statistic[batch.ends[fast]]
        self._restart(rows[self._C[rows] <= 0.0])
        looped = np.empty(len(slots), bool)
        looped[batch.order] = slow[batch.group]
        return looped

    def _loop(self, slots, codes, g, sequence):
        """
        Run the capped statistic row by row for the other landmarks (as ``compiled.cusum``).

        Return ``_raise`` of the landmarks that raised an alarm, in the order raised.
        """
        alarms: List[Tuple[int, int]] = []
        if not len(slots):
            return []
        batch = Groups(slots)
        for k in range(batch.count):
            slot = int(batch.unique[k])
            rows = batch.order[batch.starts[k]:batch.ends[k] + 1]
            evidence = self._E[slot].tolist()
            statistic, first = float(self._C[slot]), int(self._first[slot])
            for code, gain, number in zip(codes[rows].tolist(), g[rows].tolist(),
                                          sequence[rows].tolist()):
                if statistic <= 0.0:
                    first = number
                # C = sum_s min(G_s, cap): only this source's term changes.
                counted = min(evidence[code], self.cap)
                evidence[code] += gain
                statistic += min(evidence[code], self.cap) - counted
                if statistic <= 0.0:
                    evidence, statistic = [0.0] * len(evidence), 0.0
                elif statistic >= self.threshold * (1.0 - 1e-12):
                    alarms.append((number, slot))
                    break
            self._E[slot], self._C[slot], self._first[slot] = evidence, max(statistic, 0.0), first
        alarms.sort()
        return self._raise(np.array([slot for _, slot in alarms], np.int64))

    def _raise(self, slots):
        """
        Count the alarms of ``slots`` (in the order raised), restart their tests.

        Return ``(landmark ID, first sequence number of its post-change rows)`` of each.
        """
        alarms = [(int(self._ids[slot]), int(self._first[slot])) for slot in slots.tolist()]
        for landmark_id, _ in alarms:
            self.alarms[landmark_id] += 1
        self._restart(slots)
        return alarms


def move_detector(config: Any, clip: float) -> Optional[MoveDetector]:
    """
    Return the change detection a ``FuserConfig`` asks for (None when it is off).

    ``move_false_alarm_rate`` (0: off), ``move_shift_sigma`` and the rows' noise model
    ``noise_correlation_time_s``, ``range_correlated_fraction``,
    ``bearing_correlated_fraction``; ``clip`` is the map's gate threshold.
    """
    if not config.move_false_alarm_rate:
        return None
    return MoveDetector(config.move_false_alarm_rate, config.move_shift_sigma, clip,
                        NoiseModel(config.noise_correlation_time_s,
                                   config.range_correlated_fraction,
                                   config.bearing_correlated_fraction),
                        config.move_min_sources)


def detect_moves(detector: MoveDetector, landmark_map: Any, tested: NDArray[np.bool_],
                 rows: Tuple[NDArray[Any], ...], result: UpdateResult,
                 names: Optional[Sequence[str]] = None,
                 groups: Optional[Tuple[NDArray[np.int64], NDArray[np.intp]]] = None
                 ) -> List[int]:
    """
    Feed one update's rows to the tests; rebuild the landmarks that moved; return their IDs.

    The tests take the innovations of the detector's reference filters
    (``fuser.change_reference``), for the rows of landmarks that were confirmed before
    the update; a landmark whose test raised an alarm restarts its filter.

    Parameters
    ----------
    detector : MoveDetector
        The tests.
    landmark_map : MovingLandmarkMap
        The map the rows were just fused into.
    tested : ndarray of bool, shape (N,)
        The rows whose landmarks were confirmed before the update (the rows tested).
    rows : tuple
        ``ids`` (N,), ``z`` (N, 2) [m], ``P``, ``P_dep`` (N, 2, 2) [m^2], source names
        (N,) and stamps (N,) [ns] of the update's rows.
    result : UpdateResult
        The update's result: landmarks it confirmed or rebuilt restart their tests and
        their rows are left out.
    names : sequence of str, optional
        When given, the source column of ``rows`` holds indices into it (int, (N,)).
    groups : tuple, optional
        ``core.arrays.unique_inverse(ids)``, when the caller has it.

    Returns
    -------
    list of int
        The IDs rebuilt from their post-change rows, in ID order.

    """
    ids, z, P, P_dep, sources, stamps = rows
    groups = unique_inverse(ids) if groups is None else groups
    fresh = list(result.confirmed) + list(result.reinitialised)
    taken = np.asarray(tested, bool).copy()
    if fresh:
        detector.reset(fresh)
        taken &= ~np.isin(ids, fresh)
    white = np.full(len(ids), np.nan)
    if taken.any():
        named = sources if names is None or not detector.reference.correlated else (
            np.asarray(names)[sources])
        every = bool(taken.all())

        def pick(x):
            return np.asarray(x) if every else np.asarray(x)[taken]
        white[taken] = detector.reference.innovations(
            ids[taken], pick(z), pick(P), pick(P_dep), pick(named), pick(stamps),
            groups if every else subset(groups, taken))
    moved = []
    for alarm in detector.observe(ids, white, (z, P - P_dep, P_dep, sources, stamps), names,
                                  groups):
        detector.reference.reset([alarm.landmark_id])
        if landmark_map.rebuild(alarm.landmark_id, alarm.observations):
            moved.append(alarm.landmark_id)
    return moved
