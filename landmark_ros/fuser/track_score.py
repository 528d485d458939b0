"""
Track scores: the sequential probability ratio test of a track against clutter (ROS-free).

A tentative track (``fuser.tracks``) carries a score ``L``: the log-likelihood ratio of
its rows under "a landmark" (H1) against "clutter" (H0) (Blackman and Popoli, "Design
and Analysis of Modern Tracking Systems", 1999, sec. 6.2). Per message of a source, a
track in the source's view either gets a row or not.

Hit. Under H1 the row ``z`` is a detection (probability ``P_D``) with density
``N(z; m, S)``, ``S = P + R`` (track estimate plus row noise); under H0 it is a
clutter row, Poisson with ``lambda`` rows per unit area per message, uniform over the
view, so its density per message is ``lambda``. The ratio gives::

    dL_hit = ln(P_D / lambda) - (d^2 + ln|2 pi S|) / 2,   d^2 = (z - m)' S^-1 (z - m)

Miss. The track was in view and got no row: ``P(no row | H1) = 1 - P_D``, and under H0
nothing was there to miss (probability 1)::

    dL_miss = ln(1 - P_D)

Start. The first row of a track is a new landmark or clutter; its score is the log
prior odds of a row that starts a track being a landmark, from the team's
history: ``L0 = ln((confirmed + 1) / (deleted + 1))`` (tracks started by the team's
rows that were confirmed, deleted; ``start_score``), bounded to
``[ln(START_ODDS_MIN), 0]``.

Decision (Wald's sequential probability ratio test, with ``alpha`` the probability of
confirming clutter and ``beta`` that of deleting a landmark): confirm when
``L >= ln((1 - beta) / alpha)``, delete when ``L <= ln(beta / (1 - alpha))``
(``sprt_thresholds``).

Estimators (``SourceStatistics``, per source, from the data, persisted in the map file):

range ``r`` [m]
    The farthest row of the source paired with a confirmed landmark (any row until one
    was), from the robot position the message was observed from (``Scan.robot_xy``).
field of view ``phi`` [rad]
    Half its width: the largest ``|bearing|`` of those rows from the sensor heading
    (``Scan.heading``), over the messages that carry a heading. The view of a message
    is the sector of radius ``r`` and half-angle ``phi`` about its heading
    (``SourceStatistics.in_view``); a message without a heading, or before a row of the
    source went to a confirmed landmark, has the disc of radius ``r`` (``phi = pi``:
    the largest bearing of a few unpaired rows says little about the field of view). A
    landmark outside its message's view is not expected to be seen: it neither hits
    nor misses. Both are maxima, so they only grow (a row of a
    wrong pairing at a larger range or bearing widens them for good).
clutter density ``lambda`` [rows / m^2 / message]
    ``(c + PRIOR_CLUTTER_ROWS) / (A + PRIOR_CLUTTER_ROWS / PRIOR_CLUTTER_DENSITY)``:
    ``c`` the rows not paired with a confirmed landmark, less the rows of tracks that
    were confirmed later (they were landmarks), ``A`` the sum over messages of the view's
    area ``phi r^2``; the gamma-Poisson posterior mean with the prior as pseudo-counts;
    bounded to ``[DENSITY_MIN, DENSITY_MAX]``.
detection probability ``P_D``
    ``(h + 1) / (e + 2)``: ``e`` the confirmed landmarks in the view of the source's
    messages, ``h`` how many of them got a row (the beta posterior mean from a uniform
    prior); bounded to ``[P_D_MIN, P_D_MAX]``. A landmark with a row in its gate that
    another landmark took counts as expected and not detected (leaving it out would
    drop exactly the scans that see one landmark of a close pair and not the other,
    and push the estimate of such pairs to 1); only the score spares it the miss. It scores
    the misses and hits here and is the ``P_D`` of the merge test
    (``fuser.tracks.Tracker.one_landmark``, pooled over the sources:
    ``team_detection_probability``).

Messages without a ``Scan`` (no robot position) give no view: their rows score hits
with the current estimates, and no misses.
"""

from dataclasses import dataclass, fields
from typing import Any, Dict, Iterable, Optional, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy.stats import binom

PRIOR_CLUTTER_DENSITY = 0.01
"""Prior clutter density [rows / m^2 / message]: one row per 100 m^2 of view."""
PRIOR_CLUTTER_ROWS = 1.0
"""Weight of that prior, in rows."""
DENSITY_MIN, DENSITY_MAX = 1e-6, 100.0
"""Bounds of the clutter density estimate [rows / m^2 / message]."""
P_D_MIN, P_D_MAX = 0.05, 0.99
"""Bounds of the detection probability estimate."""
START_ODDS_MIN = 1e-3
"""Lowest prior odds of a track's first row being a landmark (``L0 >= ln`` of it)."""


def sprt_thresholds(alpha: float, beta: float) -> Tuple[float, float]:
    """
    Return Wald's thresholds ``(confirm, delete)`` of the track score.

    Parameters
    ----------
    alpha : float
        Probability of confirming a clutter track, in (0, 1).
    beta : float
        Probability of deleting a landmark's track, in (0, 1), ``alpha + beta < 1``.

    Returns
    -------
    tuple of float
        ``ln((1 - beta) / alpha)`` and ``ln(beta / (1 - alpha))``.

    Raises
    ------
    ValueError
        If ``alpha`` or ``beta`` is outside (0, 1) or their sum is not below 1.

    """
    if not (0.0 < alpha < 1.0 and 0.0 < beta < 1.0 and alpha + beta < 1.0):
        raise ValueError(f'alpha {alpha!r} and beta {beta!r} must be in (0, 1), sum below 1')
    return float(np.log((1.0 - beta) / alpha)), float(np.log(beta / (1.0 - alpha)))


def hit_increments(z: NDArray[np.float64], m: NDArray[np.float64], S: NDArray[np.float64],
                   P_D: float, clutter_density: float) -> NDArray[np.float64]:
    """
    Return the score increments of rows paired with tracks (the module's ``dL_hit``).

    Parameters
    ----------
    z : ndarray, shape (N, 2) [m]
        The rows.
    m : ndarray, shape (N, 2) [m]
        The means of their tracks.
    S : ndarray, shape (N, 2, 2) [m^2]
        Innovation covariances (track plus row).
    P_D : float
        Detection probability, in (0, 1).
    clutter_density : float
        Clutter rows per unit area per message [1 / m^2], positive.

    Returns
    -------
    ndarray, shape (N,)

    """
    nu = np.asarray(z, np.float64) - np.asarray(m, np.float64)
    S = np.asarray(S, np.float64)
    d2 = np.einsum('ni,ni->n', nu, np.linalg.solve(S, nu[..., None])[..., 0])
    _, logdet = np.linalg.slogdet(2.0 * np.pi * S)
    return np.log(P_D / clutter_density) - 0.5 * (d2 + logdet)


def start_score(confirmed: int, deleted: int) -> float:
    """
    Return the score of a track's first row, ``L0``: the log prior odds of a landmark.

    ``ln((confirmed + 1) / (deleted + 1))`` over the tracks the team's rows started
    (pooled: the first robot to see a landmark starts its track), bounded to
    ``[ln(START_ODDS_MIN), 0]``.
    """
    odds = (confirmed + 1.0) / (deleted + 1.0)
    return float(np.log(np.clip(odds, START_ODDS_MIN, 1.0)))


def miss_increment(P_D: float) -> float:
    """Return the score increment of a track in view that got no row: ``ln(1 - P_D)``."""
    return float(np.log1p(-P_D))


@dataclass
class SourceStatistics:
    """What one source's data say about its view, clutter and detections (module doc)."""

    range_m: float = 0.0
    """Radius of the view [m] (0: none seen yet)."""
    paired_range: bool = False
    """Whether ``range_m`` comes from rows paired with confirmed landmarks."""
    half_view_rad: float = 0.0
    """Half the width of the field of view [rad] (0: none seen yet)."""
    paired_view: bool = False
    """Whether ``half_view_rad`` comes from rows paired with confirmed landmarks."""
    clutter_rows: float = 0.0
    """Rows not paired with a confirmed landmark, less those of tracks confirmed later."""
    area: float = 0.0
    """Sum of the view areas of the messages [m^2]."""
    expected: int = 0
    """Confirmed landmarks in the view of the messages."""
    detected: int = 0
    """Of those, the ones that got a row."""
    confirmed: int = 0
    """Tracks the source started that were confirmed."""
    deleted: int = 0
    """Tracks the source started that were deleted."""

    @property
    def clutter_density(self) -> float:
        """Return the clutter density estimate [rows / m^2 / message], bounded."""
        prior_area = PRIOR_CLUTTER_ROWS / PRIOR_CLUTTER_DENSITY
        value = (max(self.clutter_rows, 0.0) + PRIOR_CLUTTER_ROWS) / (self.area + prior_area)
        return float(np.clip(value, DENSITY_MIN, DENSITY_MAX))

    @property
    def detection_probability(self) -> float:
        """Return the detection probability estimate, bounded."""
        return float(np.clip((self.detected + 1.0) / (self.expected + 2.0),
                             P_D_MIN, P_D_MAX))

    def see(self, ranges: NDArray[np.float64], paired: NDArray[np.bool_],
            bearings: Optional[NDArray[np.float64]] = None) -> None:
        """
        Widen the view with the ranges (and bearings) of one message's rows.

        Parameters
        ----------
        ranges : ndarray, shape (N,) [m]
            Distances of the rows from the robot.
        paired : ndarray of bool, shape (N,)
            Which rows went to confirmed landmarks.
        bearings : ndarray, shape (N,) [rad], optional
            Their bearings from the sensor heading; None when the message has no heading.

        """
        self.range_m, self.paired_range = _widen(self.range_m, self.paired_range,
                                                 ranges, paired)
        if bearings is not None:
            self.half_view_rad, self.paired_view = _widen(
                self.half_view_rad, self.paired_view, np.minimum(np.abs(bearings), np.pi),
                paired)

    def view_area(self, heading: Optional[float]) -> float:
        """Return the area of a message's view [m^2]: ``phi r^2`` (or the disc's, module doc)."""
        half = self.half_view_rad if heading is not None and self.paired_view else np.pi
        return float(half * self.range_m ** 2)

    def in_view(self, xy: NDArray[np.float64], robot_xy: NDArray[np.float64],
                heading: Optional[float]) -> NDArray[np.bool_]:
        """
        Return which points lie in a message's view (module doc).

        Parameters
        ----------
        xy : ndarray, shape (K, 2) [m]
            Points in the world.
        robot_xy : ndarray, shape (2,) [m]
            Where the message was observed from.
        heading : float or None
            The sensor heading in the world [rad]; None: the disc of radius ``range_m``
            (also before ``paired_view``).

        Returns
        -------
        ndarray of bool, shape (K,)

        """
        d = np.asarray(xy, np.float64).reshape(-1, 2) - np.asarray(robot_xy, np.float64)
        near = np.hypot(d[:, 0], d[:, 1]) <= self.range_m
        if heading is None or not self.paired_view:
            return near
        return near & (np.abs(bearings_from(d, heading)) <= self.half_view_rad)

    def to_dict(self) -> Dict[str, Any]:
        """Return the fields as plain JSON data."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, document: Dict[str, Any]) -> 'SourceStatistics':
        """
        Return the statistics of ``to_dict`` (missing fields take their defaults).

        Raises
        ------
        ValueError
            If a field has the wrong type or a negative value (``clutter_rows`` aside).

        """
        values: Dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in document:
                continue
            value = document[f.name]
            if f.type in (bool, 'bool'):
                if not isinstance(value, bool):
                    raise ValueError(f'{f.name} {value!r} is not a boolean')
            elif isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    np.isfinite(value) and (value >= 0 or f.name == 'clutter_rows')):
                raise ValueError(f'{f.name} {value!r} is not a count')
            values[f.name] = int(value) if f.type in (int, 'int') else value
        return cls(**values)


def bearings_from(d: NDArray[np.float64], heading: float) -> NDArray[np.float64]:
    """Return the bearings of offsets ``d`` (K, 2) [m] from a heading [rad], in [-pi, pi)."""
    angle = np.arctan2(d[:, 1], d[:, 0]) - heading
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _widen(value: float, from_paired: bool, values: NDArray[np.float64],
           paired: NDArray[np.bool_]) -> Tuple[float, bool]:
    """Return a view bound widened by one message: the paired rows' largest, else any row's."""
    if paired.any():
        largest = float(np.max(values[paired]))
        return (max(value, largest) if from_paired else largest), True
    if len(values) and not from_paired:
        return max(value, float(np.max(values))), False
    return value, from_paired


def team_detection_probability(statistics: Iterable[SourceStatistics]) -> Optional[float]:
    """
    Return the detection probability pooled over sources, None when none saw a landmark.

    ``(sum h + 1) / (sum e + 2)`` over the sources (``SourceStatistics``), bounded to
    ``[P_D_MIN, P_D_MAX]``: each source's estimate weighted by its evidence.
    """
    statistics = list(statistics)
    expected = sum(s.expected for s in statistics)
    if not expected:
        return None
    detected = sum(s.detected for s in statistics)
    return float(np.clip((detected + 1.0) / (expected + 2.0), P_D_MIN, P_D_MAX))


def together_log_likelihood_ratio(k: int, n: int, same: float, distinct: float) -> float:
    """
    Return the log likelihood ratio of one landmark against two, from co-occurrences.

    Of ``n`` messages that gave a row to either of two tracks, ``k`` gave rows to both.
    Two distinct landmarks close enough to pass each other's gate are seen together in
    a fraction ``distinct`` of such messages (about ``p_D / (2 - p_D)`` when both are
    in view), two tracks of one landmark in a fraction ``same`` (a clutter row or a
    mis-associated row beside it). With ``k ~ Binomial(n, rate)``:
    ``k log(same / distinct) + (n - k) log((1 - same) / (1 - distinct))``; positive
    favours one landmark. ``k = 0`` always favours it (the rule "never seen together"),
    each co-occurrence costs ``log(distinct / same)``, each message that saw only one of
    them gains ``log((1 - same) / (1 - distinct))``: asymptotically, one landmark when
    ``k / n`` is below ``log((1 - same) / (1 - distinct)) / log(distinct (1 - same) /
    (same (1 - distinct)))``.

    Parameters
    ----------
    k : int
        Messages that saw both.
    n : int
        Messages that saw either, ``n >= k``.
    same, distinct : float
        The two rates, ``0 < same < distinct < 1``.

    Returns
    -------
    float

    """
    return float(k * np.log(same / distinct)
                 + (n - k) * (np.log1p(-same) - np.log1p(-distinct)))


def one_landmark_by_sightings(k: int, n: int, p_D: Optional[float], same: float,
                              tail_probability: float, threshold: float) -> bool:
    """
    Decide whether two compatible tracks are one landmark, from their co-occurrences.

    Of ``n`` messages that gave a row to either (since the two first met), ``k`` gave
    rows to both. One landmark when ``k = 0``; else when both hold:

    - "one landmark" explains ``k``: ``P(K >= k)`` for ``K ~ Binomial(n, same)`` is at
      least ``tail_probability`` (a second track that meets the first in a good share of
      its messages is a second landmark, whatever ``p_D``; such a pair's one track may
      have taken both landmarks' rows, which drives ``p_D`` towards 1);
    - ``together_log_likelihood_ratio(k, n, same, p_D / (2 - p_D))`` reaches
      ``threshold``.

    Without ``p_D`` (None or 0), or with ``p_D / (2 - p_D)`` not above ``same``, tracks
    that met are kept apart.

    Parameters
    ----------
    k, n : int
        Messages that saw both, messages that saw either, ``0 <= k <= n``.
    p_D : float or None
        Detection probability of a landmark in view.
    same : float
        Rate of meetings of two tracks of one landmark, in (0, 1).
    tail_probability : float
        Smallest probability of ``k`` or more meetings for "one landmark".
    threshold : float
        Smallest log-likelihood ratio that merges.

    Returns
    -------
    bool

    """
    if k == 0:
        return True
    if not p_D or p_D / (2.0 - p_D) <= same:
        return False
    if binom.sf(k - 1, n, same) < tail_probability:
        return False
    return together_log_likelihood_ratio(k, n, same, p_D / (2.0 - p_D)) >= threshold
