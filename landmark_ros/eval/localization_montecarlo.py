"""
Monte Carlo of the localizer on simulated worlds: the pose NEES and its interval.

Each seed draws a world (``sim.simulation.generate_world``: 15 landmarks in 20 m), one
loop path at 0.5 m/s (``make_paths``), wheel odometry at 50 Hz with the odometry model's
noise (``sim.odometry``), and range-bearing sightings of the visible landmarks (8 m,
all around) every 0.2 s with white noise. The map is the true landmarks with a small
stated covariance (independent of the robot: the plain EKF update); the localizer
uses the same alphas and noise (the models are exact up to the linearisation). Per
seed the average NEES of the 3-dof pose over the run (after the first 2 s); over the
seeds their mean and its 95 % interval (normal approximation of the seed means):
consistent when the interval holds 3.

With ``--map-stddev S`` the map the localizer holds is off the truth by N(0, S^2) per
coordinate, drawn once per seed, and states that covariance: the same error at every
sighting, which ``--correlation consider`` (the Schmidt-Kalman update,
``localizer.consider``) accounts for, ``independent`` counts again at every sighting
(over-confident) and ``split_ci`` bounds at every update.

With ``--hide-ids take|merge`` every landmark has a partner ``PAIR_M`` away (random
direction, as MRCLAM's pairs) and the rows come without IDs: the localizer associates
them (JCBB), its ambiguous rows taking JCBB's choice (``take``) or applied once per
candidate (``merge``, ``association_merge_ambiguous``).

Run: ``python -m landmark_ros.eval.localization_montecarlo [--seeds 20] [--hide-ids
merge] [--map-stddev 0.1 --correlation consider]``.
"""

import argparse
import math
import sys

from landmark_ros.localizer import motion
from landmark_ros.localizer.config import CORRELATIONS, LocalizerConfig
from landmark_ros.localizer.localizer import Localizer, UNKNOWN_ID
from landmark_ros.sim.odometry import wheel_odometry
from landmark_ros.sim.simulation import generate_world, make_paths, visible
import numpy as np

ALPHAS = (0.05, 0.5, 0.05, 0.01)
PAIR_M = 0.25
"""Distance of each landmark's partner with ``--hide-ids`` [m]."""
RANGE_STDDEV, BEARING_STDDEV = 0.05, 0.02
MS = 1_000_000


def _paired(world, generator):
    """Return ids, positions of the world's landmarks and a partner of each."""
    angle = generator.uniform(0.0, 2.0 * math.pi, len(world.ids))
    partners = world.positions + PAIR_M * np.column_stack([np.cos(angle), np.sin(angle)])
    ids = np.concatenate([world.ids, world.ids.max() + 1 + np.arange(len(world.ids))])
    return ids, np.vstack([world.positions, partners])


def run_seed(seed, duration_s=60.0, rate_hz=50.0, hidden=None, map_stddev=0.0,
             correlation='independent'):
    """
    Return the average pose NEES of one seed and the rows used.

    ``hidden``, ``map_stddev`` [m] and ``correlation``: the module docstring.
    """
    generator = np.random.default_rng(seed)
    world = generate_world(15, 20.0, seed)
    ids, positions = (_paired(world, generator) if hidden
                      else (world.ids, world.positions))
    variance = max(map_stddev, 1e-3) ** 2
    held = (positions + generator.normal(0.0, map_stddev, positions.shape) if map_stddev > 0.0
            else positions)
    path = make_paths(1, world.bounds, 0.5, seed)[0]
    times = np.arange(0.0, duration_s, 1.0 / rate_hz)
    truth = np.array([path.pose(t) for t in times]).reshape(-1, 3)
    odom = wheel_odometry(truth, ALPHAS, generator)
    config = LocalizerConfig(odometry_alphas=ALPHAS, range_stddev=RANGE_STDDEV,
                             range_stddev_per_m=0.0, bearing_stddev=BEARING_STDDEV,
                             initial_stddev=(0.05, 0.05, 0.02),
                             correlation=correlation, association_take_ambiguous=True,
                             association_merge_ambiguous=hidden == 'merge')
    loc = Localizer(config)
    loc.set_map(ids, held, np.tile(np.eye(2) * variance, (len(ids), 1, 1)))
    start = truth[0] + generator.normal(0.0, config.initial_stddev)
    loc.initialize(0, start, np.diag(np.square(config.initial_stddev)))
    every = int(round(0.2 * rate_hz))
    nees = []
    for k, t in enumerate(times):
        stamp = int(round(t * 1e9))
        est = loc.add_odometry(stamp, pose=odom[k])
        if k % every == every // 2:
            mask, z = visible(truth[k], positions, 0.5, 8.0, 2.0 * math.pi)
            z = z[mask] + generator.normal(0.0, [RANGE_STDDEV, BEARING_STDDEV],
                                           (int(mask.sum()), 2))
            loc.add_observations(stamp, np.full(int(mask.sum()), UNKNOWN_ID, np.int64)
                                 if hidden else ids[mask], z)
            est = loc.estimate()
        if t >= 2.0 and est is not None:
            e = est.x - truth[k]
            e[2] = motion.wrap(e[2])
            nees.append(float(e @ np.linalg.solve(est.P, e)))
    return float(np.mean(nees)), loc.counters['rows_used']


def run(seeds=20, hidden=None, map_stddev=0.0, correlation='independent'):
    """Return the seed means, their mean and its 95 % interval."""
    means = np.array([run_seed(seed, hidden=hidden, map_stddev=map_stddev,
                               correlation=correlation)[0] for seed in range(seeds)])
    half = 1.96 * means.std(ddof=1) / math.sqrt(len(means)) if len(means) > 1 else math.inf
    return means, float(means.mean()), (float(means.mean() - half),
                                        float(means.mean() + half))


def main(argv=None):
    """Print the Monte Carlo result; exit 1 when 3 is outside the interval."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--seeds', type=int, default=20)
    parser.add_argument('--hide-ids', choices=('take', 'merge'), default=None,
                        help='landmarks in pairs, rows without IDs (module docstring)')
    parser.add_argument('--map-stddev', type=float, default=0.0,
                        help='the held map is off the truth by this much per coordinate [m]')
    parser.add_argument('--correlation', choices=CORRELATIONS, default='independent',
                        help="the localizer's map correlation")
    args = parser.parse_args(argv)
    means, mean, (low, high) = run(args.seeds, args.hide_ids, args.map_stddev,
                                   args.correlation)
    inside = low <= 3.0 <= high
    print(f'pose ANEES over {args.seeds} seeds: {mean:.2f} (95 % interval {low:.2f} to '
          f'{high:.2f}; 3 is consistent: {"inside" if inside else "outside"})')
    return 0 if inside else 1


if __name__ == '__main__':
    sys.exit(main())
