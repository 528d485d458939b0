"""
Benchmark data association of unlabelled rows into a large map, each method side by side.

A map of ``K`` landmarks (10,000 by default, uniform over a square at 10 m mean
spacing, 4 classes, covariances of 5 to 20 cm standard deviation) and ``M`` messages
of one robot: each sees its nearest landmarks (90 rows) plus clutter (10 rows),
through a shared pose error drawn from ``P_pose`` and range-bearing noise, placed in
the world by ``landmarks.landmark_to_world`` from the pose estimate. Per message,
from the same rows in the same run:

- ``nn``, ``gnn``: ``candidates`` (kd-tree) then ``nearest_neighbour`` or
  ``global_nearest_neighbour``;
- ``jcbb``: ``scan_covariance``, ``candidates``, then ``jcbb``;
- ``brute NN``: every row against every landmark (all pairs, vectorised numpy),
  class mask, gate, smallest d2; its assignments must equal ``nn``'s.

Throughput is rows per second of wall time (the targets), the best of several
passes over all messages (one pass for the brute force, on a prefix), and beside it
rows per second of this process's CPU time, which a loaded machine does not depress.
Accuracy is the fraction of rows given their true landmark (or none, for clutter).
Two scenes: ``nominal`` (the targets) and ``heading`` (a 10x larger heading
uncertainty, where the rows' shared error matters; figures only). BLAS runs
single-threaded (``OPENBLAS_NUM_THREADS=1`` unless set): the matrices are small, and
threads only contend. Targets are printed
with PASS/FAIL; the script exits 0 whatever the result. The last line is
machine-readable::

    RESULT bench_association key=value ...

Run from the repository root with the package importable (``make bench`` does this
in the dev venv): ``python bench/bench_association.py [--messages M] [--landmarks K]``.
"""

import argparse
import gc
import os
import sys
import time

import _common

for _variable in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')

from landmark_ros.core import association, joint_compatibility, landmarks  # noqa: E402
from landmark_ros.core.gating import chi2_threshold  # noqa: E402
import numpy as np  # noqa: E402

TARGET_GNN_ROWS_PER_S = 100_000.0
"""GNN throughput target, candidates included [rows/s]."""

TARGET_JCBB_ROWS_PER_S = 20_000.0
"""JCBB throughput target, scan covariance and candidates included [rows/s]."""

ROWS_SEEN = 90
"""Landmark rows per message (the nearest landmarks)."""

ROWS_CLUTTER = 10
"""Clutter rows per message."""

SIDE = 1000.0
"""Side of the square map [m]."""

R_OBS = np.diag([0.05, 0.005]) ** 2
"""Range-bearing noise of the sensor [m^2, rad^2]."""


def make_map(k, seed):
    """
    Draw the map: means, covariances and classes.

    Parameters
    ----------
    k : int
        Landmarks.
    seed : int
        Seed of ``numpy.random.default_rng``.

    Returns
    -------
    m_map : ndarray, shape (k, 2) [m]
    P_map : ndarray, shape (k, 2, 2) [m^2]
    classes : ndarray of int, shape (k,)

    """
    rng = np.random.default_rng(seed)
    side = SIDE * np.sqrt(k / 10_000)
    m_map = rng.uniform(0.0, side, (k, 2))
    sigma = rng.uniform(0.05, 0.2, (k, 2))
    angle = rng.uniform(0.0, np.pi, k)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], 1)
    P_map = rotation @ (sigma[:, :, None] ** 2 * np.eye(2)) @ np.swapaxes(rotation, 1, 2)
    return m_map, P_map, rng.integers(0, 4, k)


def make_messages(m_map, classes_map, count, P_pose, seed):
    """
    Draw the messages of one robot: rows, their covariance, pose, truth.

    Parameters
    ----------
    m_map : ndarray, shape (K, 2)
        Landmark means (the truth here).
    classes_map : ndarray of int, shape (K,)
        Landmark classes.
    count : int
        Messages.
    P_pose : ndarray, shape (3, 3)
        Covariance of the robot pose error.
    seed : int
        Seed of ``numpy.random.default_rng``.

    Returns
    -------
    list of dict
        ``z`` (N, 2), ``R`` (N, 2, 2), ``classes`` (N,), ``robot_xy`` (2,),
        ``truth`` (N,) (landmark or -1).

    """
    rng = np.random.default_rng(seed)
    side = m_map.max()
    messages = []
    for _ in range(count):
        pose = np.array([*rng.uniform(0.1 * side, 0.9 * side, 2), rng.uniform(-np.pi, np.pi)])
        estimate = pose + rng.multivariate_normal(np.zeros(3), P_pose)
        offset = m_map - pose[:2]
        seen = np.argsort(np.hypot(offset[:, 0], offset[:, 1]))[:ROWS_SEEN]
        ranges = np.hypot(offset[seen, 0], offset[seen, 1])
        bearings = np.arctan2(offset[seen, 1], offset[seen, 0]) - pose[2]
        reach = ranges.max()
        obs = np.vstack([np.column_stack([ranges, bearings]),
                         np.column_stack([rng.uniform(1.0, reach, ROWS_CLUTTER),
                                          rng.uniform(-np.pi, np.pi, ROWS_CLUTTER)])])
        obs += rng.multivariate_normal(np.zeros(2), R_OBS, len(obs))
        z, R = landmarks.landmark_to_world(estimate, P_pose, obs, R_OBS)
        messages.append({
            'z': z, 'R': R, 'robot_xy': estimate[:2],
            'classes': np.concatenate([classes_map[seen],
                                       rng.integers(0, 4, ROWS_CLUTTER)]),
            'truth': np.concatenate([seen, np.full(ROWS_CLUTTER, -1)]),
        })
    return messages


def brute_force_nn(m_map, P_map, classes_map, z, R, classes, threshold):
    """
    Pair each row with its nearest landmark by d2 over all pairs (the baseline).

    Parameters
    ----------
    m_map, P_map, classes_map : ndarray
        The map, shapes (K, 2), (K, 2, 2), (K,).
    z, R, classes : ndarray
        The rows, shapes (N, 2), (N, 2, 2), (N,).
    threshold : float
        Gate on d2.

    Returns
    -------
    ndarray of int, shape (N,)
        Landmark of each row, -1 for none.

    """
    a = R[:, None, 0, 0] + P_map[None, :, 0, 0]
    b = R[:, None, 0, 1] + P_map[None, :, 0, 1]
    c = R[:, None, 1, 1] + P_map[None, :, 1, 1]
    dx = z[:, None, 0] - m_map[None, :, 0]
    dy = z[:, None, 1] - m_map[None, :, 1]
    d2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * c - b * b)
    d2[classes[:, None] != classes_map[None, :]] = np.inf
    best = np.argmin(d2, axis=1)
    return np.where(d2[np.arange(len(z)), best] <= threshold, best, -1)


def run_scene(index, messages, P_pose, passes, brute_messages):
    """
    Time every method over the messages and score it against the truth.

    Parameters
    ----------
    index : association.LandmarkIndex
        The map.
    messages : list of dict
        From ``make_messages``.
    P_pose : ndarray, shape (3, 3)
        Pose covariance the messages carry.
    passes : int
        Timed passes over all messages (best one kept).
    brute_messages : int
        Messages for the brute force (one pass).

    Returns
    -------
    dict
        Per method: ``rows_per_s``, ``accuracy``; and ``fallbacks``, ``ambiguous``,
        ``nodes_max``, ``brute_agrees``.

    """
    rows = sum(len(msg['z']) for msg in messages)

    def nn(msg):
        return association.nearest_neighbour(
            association.candidates(index, msg['z'], msg['R'], msg['classes']))

    def gnn(msg):
        return association.global_nearest_neighbour(
            association.candidates(index, msg['z'], msg['R'], msg['classes']))

    def jcbb(msg):
        C_z = association.scan_covariance(msg['z'], msg['R'], msg['robot_xy'], P_pose)
        cands = association.candidates(index, msg['z'], msg['R'], msg['classes'])
        return joint_compatibility.jcbb(cands, index, msg['z'], C_z)

    figures = {}
    for name, method in (('nn', nn), ('gnn', gnn), ('jcbb', jcbb)):
        method(messages[0])
        best, best_cpu, results = float('inf'), float('inf'), None
        gc.disable()
        try:
            for _ in range(passes):
                start, start_cpu = time.perf_counter(), time.process_time()
                results = [method(msg) for msg in messages]
                best = min(best, time.perf_counter() - start)
                best_cpu = min(best_cpu, time.process_time() - start_cpu)
        finally:
            gc.enable()
        correct = sum(int(np.sum(r.assignment == msg['truth']))
                      for r, msg in zip(results, messages))
        figures[name] = {'rows_per_s': rows / best, 'cpu_rows_per_s': rows / best_cpu,
                         'accuracy': correct / rows, 'results': results}
    jcbb_results = figures['jcbb'].pop('results')
    figures['fallbacks'] = sum(r.fallback for r in jcbb_results)
    figures['ambiguous'] = sum(len(r.ambiguous) for r in jcbb_results)
    figures['nodes_max'] = max(r.nodes for r in jcbb_results)
    nn_results = figures['nn'].pop('results')
    figures['gnn'].pop('results')

    threshold = chi2_threshold(2, association.DEFAULT_PROBABILITY)
    subset = messages[:brute_messages]
    start, start_cpu = time.perf_counter(), time.process_time()
    brute = [brute_force_nn(index.m_map, index.P_map, index.classes, msg['z'], msg['R'],
                            msg['classes'], threshold) for msg in subset]
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    brute_rows = sum(len(msg['z']) for msg in subset)
    correct = sum(int(np.sum(b == msg['truth'])) for b, msg in zip(brute, subset))
    figures['brute_nn'] = {'rows_per_s': brute_rows / seconds,
                           'cpu_rows_per_s': brute_rows / cpu_seconds,
                           'accuracy': correct / brute_rows}
    figures['brute_agrees'] = all(np.array_equal(b, r.assignment)
                                  for b, r in zip(brute, nn_results))
    return figures


def report_scene(title, figures):
    """Return the report lines of one scene."""
    lines = [title]
    base = figures['brute_nn']['rows_per_s']
    for name, label in (('brute_nn', 'brute-force NN (all pairs)'), ('nn', 'NN (kd-tree)'),
                        ('gnn', 'GNN'), ('jcbb', 'JCBB')):
        f = figures[name]
        lines.append(f'  {label:28s} {f["rows_per_s"]:10.4g} rows/s wall '
                     f'({f["rows_per_s"] / base:6.1f}x brute), {f["cpu_rows_per_s"]:10.4g} '
                     f'rows/s CPU  accuracy {f["accuracy"]:.4f}')
    lines.append(f'  JCBB: {figures["fallbacks"]} fallbacks to GNN, {figures["ambiguous"]} '
                 f'ambiguous rows, at most {figures["nodes_max"]} nodes per message; '
                 f'brute-force NN equals kd-tree NN: '
                 f'{_common.verdict(figures["brute_agrees"])}')
    return lines


def main(argv=None):
    """
    Run the benchmark, print the report and return the figures.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments without the program name; ``None`` reads ``sys.argv``.

    Returns
    -------
    dict
        ``nominal`` and ``heading`` (see ``run_scene``), ``targets`` (name to bool),
        ``seconds``.

    """
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--landmarks', type=int, default=10_000,
                        help='landmarks in the map (default 10000)')
    parser.add_argument('--messages', type=int, default=200,
                        help='messages of 100 rows per scene (default 200)')
    parser.add_argument('--passes', type=int, default=3,
                        help='timed passes over the messages, best kept (default 3)')
    parser.add_argument('--brute-messages', type=int, default=40,
                        help='messages for the brute force (default 40)')
    parser.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    args = parser.parse_args(argv)
    started = time.perf_counter()
    load_start = os.getloadavg()[0]
    m_map, P_map, classes_map = make_map(args.landmarks, args.seed)
    start = time.perf_counter()
    index = association.LandmarkIndex(m_map, P_map, classes_map)
    build_ms = (time.perf_counter() - start) * 1e3

    scenes = {
        'nominal': np.diag([0.05, 0.05, 0.002]) ** 2,
        'heading': np.diag([0.05, 0.05, 0.02]) ** 2,
    }
    figures = {}
    for offset, (name, P_pose) in enumerate(scenes.items()):
        messages = make_messages(m_map, classes_map, args.messages, P_pose,
                                 args.seed + 1 + offset)
        figures[name] = run_scene(index, messages, P_pose, args.passes,
                                  min(args.brute_messages, args.messages))
    nominal = figures['nominal']
    targets = {
        'gnn_rows_per_s': nominal['gnn']['rows_per_s'] >= TARGET_GNN_ROWS_PER_S,
        'jcbb_rows_per_s': nominal['jcbb']['rows_per_s'] >= TARGET_JCBB_ROWS_PER_S,
        'brute_agrees': nominal['brute_agrees'] and figures['heading']['brute_agrees'],
    }
    seconds = time.perf_counter() - started
    host = _common.machine()
    blas = os.environ.get('OPENBLAS_NUM_THREADS')
    lines = [
        f'bench_association: {args.landmarks} landmarks, {args.messages} messages of '
        f'{ROWS_SEEN + ROWS_CLUTTER} unlabelled rows ({ROWS_CLUTTER} clutter) per scene '
        f'(seed {args.seed}); index built in {build_ms:.1f} ms',
        f'machine: {host["cpu"]}; {host["cpu_count"]} CPUs; Python {host["python"]}; '
        f'numpy {host["numpy"]}; OPENBLAS_NUM_THREADS={blas}; load average '
        f'{load_start:.1f} at start, {os.getloadavg()[0]:.1f} at end',
        '',
        *report_scene('nominal: P_pose sd 5 cm, 5 cm, 2 mrad (targets)', nominal),
        f'  target GNN >= {TARGET_GNN_ROWS_PER_S:.3g} rows/s (wall): '
        f'{_common.verdict(targets["gnn_rows_per_s"])}; target JCBB >= '
        f'{TARGET_JCBB_ROWS_PER_S:.3g} rows/s (wall): '
        f'{_common.verdict(targets["jcbb_rows_per_s"])}',
        f'  on CPU time (this process alone, what a loaded machine hides): GNN '
        f'{_common.verdict(nominal["gnn"]["cpu_rows_per_s"] >= TARGET_GNN_ROWS_PER_S)}, '
        f'JCBB {_common.verdict(nominal["jcbb"]["cpu_rows_per_s"] >= TARGET_JCBB_ROWS_PER_S)}',
        '',
        *report_scene('heading: P_pose sd 5 cm, 5 cm, 20 mrad (1 m along-track at 50 m)',
                      figures['heading']),
        '',
        f'targets: {", ".join(f"{k} {_common.verdict(v)}" for k, v in targets.items())}; '
        f'run time {seconds:.1f} s',
        'RESULT bench_association'
        f' landmarks={args.landmarks} rows_per_msg={ROWS_SEEN + ROWS_CLUTTER}'
        f' messages={args.messages}'
        f' brute_nn_rows_per_s={nominal["brute_nn"]["rows_per_s"]:.6g}'
        f' nn_rows_per_s={nominal["nn"]["rows_per_s"]:.6g}'
        f' gnn_rows_per_s={nominal["gnn"]["rows_per_s"]:.6g}'
        f' jcbb_rows_per_s={nominal["jcbb"]["rows_per_s"]:.6g}'
        f' gnn_cpu_rows_per_s={nominal["gnn"]["cpu_rows_per_s"]:.6g}'
        f' jcbb_cpu_rows_per_s={nominal["jcbb"]["cpu_rows_per_s"]:.6g}'
        f' gnn_ratio={nominal["gnn"]["rows_per_s"] / nominal["brute_nn"]["rows_per_s"]:.6g}'
        f' nn_accuracy={nominal["nn"]["accuracy"]:.6g}'
        f' gnn_accuracy={nominal["gnn"]["accuracy"]:.6g}'
        f' jcbb_accuracy={nominal["jcbb"]["accuracy"]:.6g}'
        f' heading_nn_accuracy={figures["heading"]["nn"]["accuracy"]:.6g}'
        f' heading_gnn_accuracy={figures["heading"]["gnn"]["accuracy"]:.6g}'
        f' heading_jcbb_accuracy={figures["heading"]["jcbb"]["accuracy"]:.6g}'
        f' heading_jcbb_rows_per_s={figures["heading"]["jcbb"]["rows_per_s"]:.6g}'
        f' jcbb_fallbacks={nominal["fallbacks"] + figures["heading"]["fallbacks"]}'
        f' cpus={host["cpu_count"]} numpy={host["numpy"]}'
        f' pass={int(all(targets.values()))}',
    ]
    print('\n'.join(lines))
    sys.stdout.flush()
    return {**figures, 'targets': targets, 'seconds': seconds}


if __name__ == '__main__':
    main()
    sys.exit(0)
