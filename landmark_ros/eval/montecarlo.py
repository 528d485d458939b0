"""
Monte Carlo consistency of the three fusion methods in the simulator (ROS-free).

``python -m landmark_ros.eval.montecarlo [--seeds 50] [--duration 20]`` runs the simulator
(``landmark_ros.sim.simulation``) for many seeds, pushes every measurement through the code the
nodes run (``observations.landmarks_from_rows`` at the pose the observer would
interpolate, ``LandmarkMap.update`` in stamp order) and averages the NEES of the fused
landmarks, per seed and over all seeds. A consistent estimator's average NEES is 2.
Within one seed the landmarks share the robots' pose errors and biases, so their
errors are correlated and the chi-square interval of ``2 K`` degrees of freedom (for
``K`` independent landmarks, printed for reference) is too narrow; the verdict
therefore treats the seeds as the independent samples: the mean of the per-seed
average NEES and its 95 % confidence interval (1.96 standard errors).

Two scenarios:

white
    White range-bearing noise and pose errors independent between observations:
    the product of Gaussians (``independent``) is the exact model and must be inside
    the interval; CI and split CI, which allow for correlations that are not there,
    must not be above it (conservative).
biased
    Each robot's range and bearing also carry a constant bias (the observers model
    it as the dependent part): ``independent`` treats the biased observations as
    independent and must be over-confident (above the interval); CI and split CI
    must not be above it.
"""

import argparse
from dataclasses import replace
import sys
import time

from landmark_ros.core.landmark_map import FUSION_METHODS, LandmarkMap
from landmark_ros.eval.metrics import anees_interval, evaluate
from landmark_ros.pipeline.pose_buffer import interpolate
from landmark_ros.pipeline.rows import landmarks_from_rows
from landmark_ros.sim import simulation
import numpy as np

SCENARIOS = {
    'white': {},
    'biased': {'range_bias_stddev': 0.05, 'bearing_bias_stddev': 0.01},
}
"""Changes to the simulator defaults per scenario."""

EXPECTED = {
    ('white', 'independent'): 'inside',
    ('white', 'covariance_intersection'): 'not above',
    ('white', 'split_covariance_intersection'): 'not above',
    ('biased', 'independent'): 'above',
    ('biased', 'covariance_intersection'): 'not above',
    ('biased', 'split_covariance_intersection'): 'not above',
}
"""What theory says of the pooled average NEES, per scenario and method."""


def observations(sim):
    """
    Return every robot's landmarks as the observers would publish them, in stamp order.

    Parameters
    ----------
    sim : landmark_ros.sim.simulation.Simulation
        A simulation with a finite ``duration_s``.

    Returns
    -------
    ids : ndarray of int, shape (N,)
    m, P, P_dep : ndarray, shapes (N, 2), (N, 2, 2), (N, 2, 2)
    sources : list of str, length N
    stamps : ndarray, shape (N,) [s]

    """
    config = sim.config
    R = np.diag([config.range_stddev ** 2, config.bearing_stddev ** 2])
    R_bias = None
    if config.range_bias_stddev or config.bearing_bias_stddev:
        R_bias = np.diag([config.range_bias_stddev ** 2, config.bearing_bias_stddev ** 2])
    rows = []
    count = sim.observations_until(int(config.duration_s * 1e9))
    for j in range(count):
        for robot in range(sim.robots):
            measured = sim.measure(robot, j)
            if not len(measured.ids):
                continue
            # The two poses that bracket the stamp, interpolated as the observer does.
            k = measured.stamp_ns // sim.pose_period_ns
            t0, _, pose0, P0 = sim.reported_pose(robot, k)
            t1, _, pose1, P1 = sim.reported_pose(robot, k + 1)
            pose, P_pose = interpolate(pose0, P0, pose1, P1,
                                       (measured.stamp_ns - t0) / (t1 - t0))
            kept, m, P, P_dep, _ = landmarks_from_rows(
                np.asarray(measured.ids), measured.z, R, pose, P_pose, None, R_bias)
            rows.append((np.asarray(measured.ids)[kept], m, P, P_dep,
                         f'/robot{robot + 1}/landmarks', measured.stamp_ns * 1e-9))
    return (np.concatenate([r[0] for r in rows]), np.concatenate([r[1] for r in rows]),
            np.concatenate([r[2] for r in rows]), np.concatenate([r[3] for r in rows]),
            [r[4] for r in rows for _ in range(len(r[0]))],
            np.concatenate([np.full(len(r[0]), r[5]) for r in rows]))


def run_seed(config, methods=FUSION_METHODS, gate_probability=0.999):
    """
    Simulate one seed and fuse it with each method.

    Parameters
    ----------
    config : landmark_ros.sim.simulation.SimConfig
        Simulator parameters, with the seed and a finite duration.
    methods : sequence of str
        Fusion methods.
    gate_probability : float
        The fuser's gate.

    Returns
    -------
    dict
        ``method -> list of NEES`` of the fused landmarks.

    """
    sim = simulation.Simulation(config)
    ids, m, P, P_dep, sources, stamps = observations(sim)
    truth = sim.world.truth()
    result = {}
    for method in methods:
        landmark_map = LandmarkMap(method, gate_probability, min_observations=1)
        landmark_map.update(ids, m, P, P_dep, sources, stamps)
        fused_ids, fused_m, fused_P, _, _ = landmark_map.snapshot()
        landmarks, _ = evaluate(fused_ids, fused_m, fused_P, truth)
        result[method] = [r.nees for r in landmarks]
    return result


def verdict(mean, half_width, expectation):
    """
    Return whether a mean NEES meets what theory expects of it.

    Parameters
    ----------
    mean : float
        Mean over seeds of the per-seed average NEES.
    half_width : float
        Half width of its 95 % confidence interval.
    expectation : str
        ``'inside'`` (2 in the confidence interval), ``'not above'`` (not
        significantly above 2) or ``'above'`` (significantly above 2).

    Returns
    -------
    bool

    """
    low, high = mean - half_width, mean + half_width
    return {'inside': low <= 2.0 <= high, 'not above': low <= 2.0,
            'above': low > 2.0}[expectation]


def run(seeds=50, duration_s=20.0, scenarios=tuple(SCENARIOS), methods=FUSION_METHODS,
        out=sys.stdout):
    """
    Run the Monte Carlo and print one table row per scenario and method.

    Parameters
    ----------
    seeds : int
        Seeds per scenario (0 to ``seeds - 1``).
    duration_s : float
        Simulated time per seed [s].
    scenarios : sequence of str
        Keys of ``SCENARIOS``.
    methods : sequence of str
        Fusion methods.
    out : file
        Where the table goes.

    Returns
    -------
    list of dict
        One row per scenario and method: ``scenario``, ``fusion``, ``landmarks``,
        ``anees`` (pooled), ``interval`` (its chi-square interval, for reference),
        ``seed_mean`` and ``seed_half_width`` (mean of the per-seed averages and the
        half width of its 95 % confidence interval), ``expected``, ``ok``.

    """
    rows = []
    print(f"{'scenario':<8} {'fusion':<30} {'landmarks':>9} {'ANEES':>6} {'chi2 95 %':>14} "
          f"{'seed mean':>9} {'95 % CI':>14}  expected     verdict", file=out)
    for scenario in scenarios:
        nees = {method: [] for method in methods}
        per_seed = {method: [] for method in methods}
        for seed in range(seeds):
            config = replace(simulation.SimConfig(), seed=seed, duration_s=duration_s,
                             **SCENARIOS[scenario])
            for method, values in run_seed(config, methods).items():
                nees[method] += values
                per_seed[method].append(float(np.mean(values)))
        for method in methods:
            anees = float(np.mean(nees[method]))
            interval = anees_interval(len(nees[method]))
            mean = float(np.mean(per_seed[method]))
            half = 1.96 * float(np.std(per_seed[method], ddof=1)) / np.sqrt(seeds)
            expected = EXPECTED[(scenario, method)]
            ok = verdict(mean, half, expected)
            rows.append({'scenario': scenario, 'fusion': method,
                         'landmarks': len(nees[method]), 'anees': anees, 'interval': interval,
                         'seed_mean': mean, 'seed_half_width': half,
                         'expected': expected, 'ok': ok})
            print(f'{scenario:<8} {method:<30} {len(nees[method]):9d} {anees:6.2f} '
                  f'[{interval[0]:5.2f}, {interval[1]:5.2f}] {mean:9.2f} '
                  f'[{mean - half:5.2f}, {mean + half:5.2f}]'
                  f"  {expected:<11}  {'PASS' if ok else 'FAIL'}", file=out)
    return rows


def main(argv=None):
    """Run the Monte Carlo from the command line; exit 1 if theory is contradicted."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--seeds', type=int, default=50, help='seeds per scenario')
    parser.add_argument('--duration', type=float, default=20.0,
                        help='simulated seconds per seed')
    parser.add_argument('--scenario', choices=sorted(SCENARIOS), action='append',
                        help='scenario (repeatable; default all)')
    args = parser.parse_args(argv)
    started = time.monotonic()
    print(f'Monte Carlo: {args.seeds} seeds x {args.duration:g} s simulated per scenario, '
          'three robots, 20 landmarks (simulator defaults)')
    rows = run(args.seeds, args.duration, tuple(args.scenario or SCENARIOS))
    print(f'{time.monotonic() - started:.1f} s')
    return 0 if all(row['ok'] for row in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
