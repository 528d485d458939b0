"""
Monte Carlo of change detection: a landmark that moves a little, among static ones.

``python -m landmark_ros.eval.moved_landmark [--seeds 200] [--fusion METHOD]`` (ROS-free).

Each seed has ``LANDMARKS`` labelled landmarks in a 20 m square and three robots (three
sources of one ``fuser.Fuser``, package defaults but the fusion method). At every step
each robot sends one message with a row for every landmark, seen from a pose drawn anew
(range 1 to 6 m, any bearing and heading); the fuser fuses after each message. A row's
covariances are ``core.landmarks.landmark_to_world_parts`` at that pose (range 0.1 m,
bearing 0.02 rad, pose 0.05 m and 0.01 rad: the simulator's defaults), the pose term
being the dependent part, and its error is drawn from both terms, white (the simulator's
model: ``sim.simulation``). Landmark 0 moves after ``--before`` steps by two standard
deviations of one observation: ``delta`` in a random direction with
``delta^T R^-1 delta = 4`` for ``R`` the mean total covariance of its rows (about 0.2 m).

Printed per fusion method:

- detection: the share of seeds where ``landmark_moved`` rebuilt landmark 0 within 20 of
  its post-change observations (rows of the team, counted one by one), and the delay
  distribution (rows from the move to the rebuild);
- NEES after: landmark 0's NEES against its new position ``--after`` steps after the move,
  averaged over the seeds, with the 95 % chi-square interval of that average;
- false alarms: alarms of the test on static landmarks (every landmark but 0, and landmark
  0 before its move) per 10,000 of their observations the test took, against the rate
  the threshold is set for (``move_false_alarm_rate``).
"""

import argparse
from dataclasses import dataclass, replace
import sys
import time
from typing import Optional

from landmark_ros.core.landmarks import landmark_to_world_parts
from landmark_ros.eval.metrics import anees_interval
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.pipeline.config import FuserConfig
import numpy as np

LANDMARKS = 20
"""Landmarks per seed (landmark 0 moves)."""

ROBOTS = 3
"""Robots (sources) per seed."""

WINDOW = 20
"""A move counts as detected when rebuilt within this many post-change observations."""

R_SENSOR = np.diag([0.1 ** 2, 0.02 ** 2])
"""Range-bearing noise [m^2, rad^2] (the simulator's defaults)."""

P_POSE = np.diag([0.05 ** 2, 0.05 ** 2, 0.01 ** 2])
"""Pose covariance [m^2, m^2, rad^2] (the simulator's defaults)."""


@dataclass
class SeedResult:
    """What one seed gave for one fusion method."""

    delay: Optional[int] = None
    """Post-change rows of landmark 0 up to its rebuild (None: not rebuilt)."""
    nees_after: float = float('nan')
    """Landmark 0's NEES against its new position at the end."""
    static_rows: int = 0
    """Observations of static landmarks the test took."""
    false_alarms: int = 0
    """Alarms on static landmarks."""
    moved_counted: int = 0
    """The fuser's ``landmark_moved`` counter at the end."""


def draw_rows(rng, truth):
    """
    Return one robot's rows of every landmark: ``m, P, P_dep`` from fresh poses.

    Parameters
    ----------
    rng : numpy.random.Generator
        The seed's stream.
    truth : ndarray, shape (K, 2)
        True landmark positions [m].

    Returns
    -------
    tuple of ndarray
        ``m`` (K, 2) [m], ``P`` and ``P_dep`` (K, 2, 2) [m^2].

    """
    count = len(truth)
    r = rng.uniform(1.0, 6.0, count)
    around = rng.uniform(-np.pi, np.pi, count)
    heading = rng.uniform(-np.pi, np.pi, count)
    pose = np.column_stack([truth[:, 0] - r * np.cos(around), truth[:, 1] - r * np.sin(around),
                            heading])
    bearing = np.angle(np.exp(1j * (around - heading)))
    z = np.column_stack([r, bearing])
    _, P_dep, P_ind = landmark_to_world_parts(pose, np.broadcast_to(P_POSE, (count, 3, 3)), z,
                                              np.broadcast_to(R_SENSOR, (count, 2, 2)))
    noise = np.einsum('kij,kj->ki', np.linalg.cholesky(P_dep + P_ind),
                      rng.standard_normal((count, 2)))
    return truth + noise, P_dep + P_ind, P_dep


def run_seed(seed, fusion, before=100, after=60, config=None):
    """
    Run one seed through one fuser; return its ``SeedResult``.

    Parameters
    ----------
    seed : int
        Seed of the landmarks, poses, noise and the move's direction.
    fusion : str
        Fusion method.
    before, after : int
        Steps before and after landmark 0 moves.
    config : FuserConfig, optional
        The fuser's parameters (package defaults but ``fusion`` when None).

    Returns
    -------
    SeedResult

    """
    rng = np.random.default_rng([seed, 20260])
    truth = rng.uniform(-10.0, 10.0, (LANDMARKS, 2))
    sources = [f'/robot{k + 1}/landmarks' for k in range(ROBOTS)]
    fuser = Fuser(config or FuserConfig(fusion=fusion), sources)
    ids = np.arange(LANDMARKS, dtype=np.int64)
    result = SeedResult()
    covariances = []
    post_rows = early = 0
    for step in range(before + after):
        if step == before:
            early = _alarms(fuser, 0)
            R_mean = np.mean(covariances, axis=0)
            direction = rng.standard_normal(2)
            direction /= np.linalg.norm(direction)
            truth[0] += 2.0 * direction / np.sqrt(direction @ np.linalg.solve(R_mean, direction))
        for k, source in enumerate(sources):
            m, P, P_dep = draw_rows(rng, truth)
            if step < before:
                covariances.append(P[0])
            seen = _alarms(fuser, 0), fuser.counters['landmark_moved']
            fuser.add_landmarks(source, LandmarkMessage(
                1_000_000_000 + (step * ROBOTS + k) * 10_000_000, ids, m, P, P_dep))
            fuser.fuse_queued()
            if step >= before:
                post_rows += 1
                if result.delay is None and _alarms(fuser, 0) > seen[0] and fuser.counters[
                        'landmark_moved'] > seen[1]:
                    result.delay = post_rows
    # Every landmark is confirmed by its second row (step 0): the tests take the rest.
    result.static_rows = (LANDMARKS - 1) * (before + after - 1) * ROBOTS + (before - 1) * ROBOTS
    if fuser.moves is not None:
        result.false_alarms = early + sum(
            count for key, count in fuser.moves.alarms.items() if key != 0)
    snapshot = fuser.snapshot()
    error = snapshot.m[0] - truth[0]
    result.nees_after = float(error @ np.linalg.solve(snapshot.P[0], error))
    result.moved_counted = fuser.counters['landmark_moved']
    return result


def _alarms(fuser, landmark_id):
    """Return the alarms of one landmark's test so far (0 without change detection)."""
    return 0 if fuser.moves is None else fuser.moves.alarms[landmark_id]


def summarise(results, false_alarm_rate):
    """
    Return the figures of one fusion method's seeds (the module notes say which).

    Parameters
    ----------
    results : list of SeedResult
        One per seed.
    false_alarm_rate : float
        The rate the threshold is set for (per observation).

    Returns
    -------
    dict
        ``seeds``, ``detected`` (share within ``WINDOW`` rows), ``delays`` (those
        rebuilt, any delay), ``delay_quantiles`` (10, 50, 90, 95 % of the delays, a
        missed seed counted as infinite), ``nees_mean`` and ``nees_interval``,
        ``static_rows``, ``false_alarms``, ``per_10k`` and ``nominal_per_10k``.

    """
    delays = np.array([np.inf if r.delay is None else r.delay for r in results])
    static = sum(r.static_rows for r in results)
    alarms = sum(r.false_alarms for r in results)
    nees = np.array([r.nees_after for r in results])
    return {'seeds': len(results), 'detected': float(np.mean(delays <= WINDOW)),
            'delays': delays[np.isfinite(delays)].astype(int).tolist(),
            'delay_quantiles': np.quantile(delays, [0.1, 0.5, 0.9, 0.95]).tolist(),
            'nees_mean': float(np.mean(nees)), 'nees_interval': anees_interval(len(nees)),
            'static_rows': static, 'false_alarms': alarms,
            'per_10k': 1e4 * alarms / max(static, 1), 'nominal_per_10k': 1e4 * false_alarm_rate}


def main(argv=None):
    """Run the Monte Carlo from the command line; exit 1 if a target is missed."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--seeds', type=int, default=200, help='seeds per fusion method')
    parser.add_argument('--first-seed', type=int, default=0, help='first seed')
    parser.add_argument('--fusion', choices=FUSION_METHODS, action='append',
                        help='fusion method (repeatable; default all)')
    parser.add_argument('--before', type=int, default=100, help='steps before the move')
    parser.add_argument('--after', type=int, default=60, help='steps after the move')
    args = parser.parse_args(argv)
    config = FuserConfig()
    print(f'moved landmark: {args.seeds} seeds, {LANDMARKS} landmarks, {ROBOTS} robots, '
          f'{args.before} + {args.after} steps; move_false_alarm_rate '
          f'{config.move_false_alarm_rate:g}, move_shift_sigma {config.move_shift_sigma:g}, '
          f'move_min_sources {config.move_min_sources}')
    ok = True
    for fusion in args.fusion or FUSION_METHODS:
        started = time.monotonic()
        results = [run_seed(seed, fusion, args.before, args.after,
                            replace(config, fusion=fusion))
                   for seed in range(args.first_seed, args.first_seed + args.seeds)]
        s = summarise(results, config.move_false_alarm_rate)
        low, high = s['nees_interval']
        print(f"{fusion}: detected within {WINDOW} rows {100 * s['detected']:.1f} %; delay "
              f"quantiles 10/50/90/95 % {s['delay_quantiles']}; NEES after "
              f"{s['nees_mean']:.2f} [{low:.2f}, {high:.2f}]; false alarms "
              f"{s['false_alarms']} in {s['static_rows']} static rows = "
              f"{s['per_10k']:.3f} per 10,000 (threshold set for {s['nominal_per_10k']:.2f}); "
              f'{time.monotonic() - started:.0f} s')
        print(f"  delays: {sorted(s['delays'])}")
        ok &= s['detected'] >= 0.95 and s['per_10k'] <= 1.0 and s['nees_mean'] <= high
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
