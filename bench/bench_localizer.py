"""
Benchmark the ``Localizer`` pipeline object: cost per odometry message and per sighting row.

Odometry: ``add_odometry`` with a twist, ``--steps`` messages at 50 Hz (the odometry
model, the saved step, the window pruning). Sightings: batches of ``--rows`` range-bearing
rows of a 20-landmark map, applied at the newest odometry stamp (no re-filtering) and
0.5 s late (the re-filter of the 25 steps since), plain EKF, split CI and the consider
update (``localizer.consider``); and rows without
ID against a map of pairs 0.3 m apart, ambiguous rows taking JCBB's choice or applied
once per candidate (``association_merge_ambiguous``). CPU time
(``time.thread_time``), best of ``--repeats``; the machine is shared, so the ratios
between cases taken side by side mean more than the absolute figures.

Node level (``--node-rounds``, 0 to skip), side by side in one run: a
``landmark_localizer`` process and a relay process (this script with ``--relay``: a node
that only receives ``odometry`` and republishes it as ``pose``, and receives
``observations`` and republishes them), both started by
``landmark_ros.ros.launcher`` in one private ROS domain, inputs reliable, alive for the
whole run. The driver sends ``--node-messages`` odometry messages (a 20-landmark map,
a batch of ``--rows`` sightings after every fifth) with at most 8 odometry messages in
flight (each gives one ``pose``), the relay and the localizer in turn in each round.
Cost per odometry message = CPU time of the node process (``/proc/<pid>/stat``) over
the messages; rate = poses per second at the driver. Medians over the rounds.

MRCLAM (skipped without ``../shared``): the offline localization replay of dataset 6
(surveyed map, landmark sightings, every robot): real-time factor by CPU time and by
the wall clock.

Run from the repository root in the dev venv: ``python bench/bench_localizer.py``; the
last line is machine-readable (``RESULT bench_localizer ...``).
"""

import argparse
import sys
import time

from _localizer_nodes import mrclam_real_time, node_costs, relay_main
from landmark_ros.core import sensors
from landmark_ros.localizer.config import LocalizerConfig
from landmark_ros.localizer.localizer import Localizer
import numpy as np

MS = 1_000_000


def _localizer(correlation, hidden=None):
    rng = np.random.default_rng(0)
    m = rng.uniform(-10, 10, (20, 2))
    if hidden:  # ten pairs 0.3 m apart, as MRCLAM's: rows fit both of a pair
        m[10:] = m[:10] + [0.3, 0.0]
    loc = Localizer(LocalizerConfig(correlation=correlation, association_take_ambiguous=True,
                                    association_merge_ambiguous=hidden == 'merge'))
    loc.set_map(np.arange(20), m, np.tile(np.eye(2) * 1e-3, (20, 1, 1)))
    loc.initialize(0, np.zeros(3), np.eye(3) * 0.01)
    return loc, m


def odometry_cost(steps):
    """Return CPU seconds per ``add_odometry``."""
    loc, _ = _localizer('split_ci')
    twist = np.array([0.3, 0.1])
    t0 = time.thread_time()
    for k in range(steps):
        loc.add_odometry(k * 20 * MS, twist=twist)
    return (time.thread_time() - t0) / steps


def sighting_cost(rows, batches, correlation, late_s, hidden=None):
    """
    Return CPU seconds per sighting row (batches of ``rows``, ``late_s`` behind).

    ``hidden``: None (rows with IDs), ``take`` or ``merge`` (rows without IDs against a
    map of pairs, ambiguous rows taking JCBB's choice or applied per candidate).
    """
    loc, m = _localizer(correlation, hidden)
    twist = np.array([0.3, 0.1])
    k, spent, done = 0, 0.0, 0
    for _ in range(batches):
        for _ in range(5):
            loc.add_odometry(k * 20 * MS, twist=twist)
            k += 1
        stamp = (k - 1) * 20 * MS - int(late_s * 1e9)
        est = loc.pose_at(stamp) or loc.estimate()
        ids = np.arange(rows) % len(m)
        z = sensors.observe(np.tile(est.x, (rows, 1)), m[ids]) + 0.01
        if hidden:
            ids = np.full(rows, 0xFFFFFFFF, np.int64)
        t0 = time.thread_time()
        loc.add_observations(stamp, ids, z)
        spent += time.thread_time() - t0
        done += rows
    return spent / done


def main(argv=None):
    """Run the benchmark; print the figures and a RESULT line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--steps', type=int, default=20000)
    parser.add_argument('--rows', type=int, default=4)
    parser.add_argument('--batches', type=int, default=400)
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--node-rounds', type=int, default=3,
                        help='rounds of relay/localizer node runs (0: no node benchmark)')
    parser.add_argument('--node-messages', type=int, default=1000)
    parser.add_argument('--no-mrclam', action='store_true', help='skip the MRCLAM replay')
    args = parser.parse_args(argv)
    odom = min(odometry_cost(args.steps) for _ in range(args.repeats))
    cases = {}
    for correlation in ('independent', 'split_ci', 'consider'):
        for late in (0.0, 0.5):
            cases[(correlation, late)] = min(
                sighting_cost(args.rows, args.batches, correlation, late)
                for _ in range(args.repeats))
    for hidden in ('take', 'merge'):
        cases[(f'split_ci_noid_{hidden}', 0.0)] = min(
            sighting_cost(args.rows, args.batches, 'split_ci', 0.0, hidden)
            for _ in range(args.repeats))
    print(f'odometry: {odom * 1e6:.1f} us per message (CPU)')
    for (correlation, late), cost in cases.items():
        print(f'sightings {correlation:21s} {late:.1f} s late: {cost * 1e6:.1f} us per row '
              f'(batches of {args.rows})')
    print('  (noid: rows without ID, map of pairs 0.3 m apart; take: JCBB choice, merge: '
          'per candidate)')
    extra = {'rows': args.rows}
    if args.node_rounds > 0:
        nodes = node_costs(args.node_rounds, args.node_messages, args.rows)
        print(f'nodes ({args.node_rounds} rounds of {args.node_messages} odometry messages, '
              f'a batch of {args.rows} sightings every 5th, 8 in flight; medians):')
        for kind in ('relay', 'localizer'):
            print(f'  {kind:9s} {nodes[f"{kind}_msg_per_s"]:8.0f} msg/s, '
                  f'{nodes[f"{kind}_cpu_us_per_msg"]:7.0f} us CPU per odometry message')
        print(f'  localizer / relay: {nodes["ratio"]:.2f} x the rate, CPU-time ratio relay / '
              f'localizer {nodes["cpu_ratio"]:.2f}')
        extra.update({k if 'ratio' not in k else f'node_{k}': v for k, v in nodes.items()})
    real_time = None if args.no_mrclam else mrclam_real_time()
    if real_time is None:
        print('MRCLAM: skipped (no ../shared dataset 6, or --no-mrclam)')
    else:
        print(f'MRCLAM dataset 6 localization replay (surveyed map, 5 robots): '
              f'{real_time["mrclam_real_time_cpu"]:.0f}x real time by CPU time, '
              f'{real_time["mrclam_real_time_wall"]:.0f}x by the wall clock')
        extra.update(real_time)
    print('RESULT bench_localizer'
          f' odometry_us={odom * 1e6:.4g}'
          + ''.join(f' {c}_{"late" if late else "now"}_row_us={v * 1e6:.4g}'
                    for (c, late), v in cases.items())
          + ''.join(f' {k}={v:.4g}' for k, v in extra.items()))
    return 0


if __name__ == '__main__':
    if '--relay' in sys.argv[1:2]:
        sys.exit(relay_main())
    sys.exit(main())
