"""
Benchmark ``LandmarkMap.update``: the three fusion methods side by side, and map memory.

Throughput. For each size (1,000 landmarks observed by 5 sources, 10,000 landmarks
observed by 50 sources) and each fusion method, a map is first initialised with one
observation's estimate of every landmark (source ``warmup``, loaded as records, not
timed), then fed ``--batches`` batches of 10,000 rows with random
landmark IDs and random sources, one after the other into the same map. The
observations are consistent: landmark truth plus a draw of the row's covariance; each
row's covariance is a random full 2x2 ``R`` whose dependent part is a random fraction
of it. Every method sees the same rows, batch by batch, the methods in turn (order
rotated per batch), so that a slow spell of the shared cores hits them alike. Rate =
rows / wall time of the best timed batch (after one untimed batch; on a shared
machine the others wait for a core); the CPU-time rate of the best batch
(``time.thread_time``) is printed too. The ratio to ``independent`` (and the targets)
is the median over the batches of the CPU-time ratio on the same batch; split CI's
ratio batch by batch and the sources per landmark at the end are printed too: split
CI's cost per row grows with a landmark's sources, so the ratio falls as the batches
add sources (``--batches`` sets how many).
Targets: ``split_covariance_intersection`` at least 50 % of ``independent`` and
``covariance_intersection`` at least 80 % of ``independent``, at both sizes.

Memory. In a fresh interpreter (``subprocess``, started before this process grows):
peak RSS of a ``split_covariance_intersection`` map holding 10,000 and 100,000
confirmed landmarks observed by 5 sources, from ``/proc/self/status`` ``VmHWM`` and
from ``resource.getrusage`` (which Linux carries over ``exec``, so it is an upper
bound), and the growth over the interpreter with numpy and the package imported.

Run from the repository root in the dev venv: ``python bench/bench_map.py``. The
script prints human-readable lines and a last, machine-readable line::

    RESULT bench_map key=value ...

and exits 0 whatever the result. About 30 to 60 s here.
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import _common
from landmark_ros.fusion import compiled
from landmark_ros.fusion.landmark_map import FUSION_METHODS, LandmarkMap
import numpy as np

SIZES = ((1000, 5), (10_000, 50))
"""(landmarks, sources) of the throughput cases."""

BATCH_ROWS = 10_000
"""Rows per ``update`` call."""

MEMORY_LANDMARKS = (10_000, 100_000)
"""Landmarks held by the maps whose memory is measured."""

INDEPENDENT_SOURCES = 'split_covariance_intersection/independent_sources'
"""Split CI with ``source_correlation: independent`` (the product across sources)."""

VARIANTS = FUSION_METHODS + (INDEPENDENT_SOURCES,)
"""What is timed: each fusion method, and split CI with independent sources (the
latter in a run of its own beside ``independent``: a fourth map in the rotation loads
the caches and shifts every ratio)."""

SHORT = {'independent': 'independent', 'covariance_intersection': 'ci',
         'split_covariance_intersection': 'split_ci', INDEPENDENT_SOURCES: 'split_ci_indep'}

LABELS = {INDEPENDENT_SOURCES: 'split CI, independent sources'}
"""Printed names that differ from the key."""

TARGETS = {'split_covariance_intersection': 0.5, 'covariance_intersection': 0.8,
           INDEPENDENT_SOURCES: 0.5}
"""Least throughput of a method as a fraction of ``independent``'s."""


def observations(rng, truth, ids):
    """
    Return consistent observations of the landmarks ``ids``.

    Returns
    -------
    z : ndarray, shape (N, 2)
        Truth plus a draw of ``R`` [m].
    R : ndarray, shape (N, 2, 2)
        Random full covariances, standard deviations 5 to 30 cm [m^2].
    R_dep : ndarray, shape (N, 2, 2)
        Their dependent part: 20 to 80 % of ``R``.

    """
    count = len(ids)
    A = rng.normal(0.0, 0.2, (count, 2, 2))
    R = A @ np.swapaxes(A, 1, 2) + 0.05 ** 2 * np.eye(2)
    R_dep = rng.uniform(0.2, 0.8, (count, 1, 1)) * R
    z = truth[ids] + (np.linalg.cholesky(R) @ rng.standard_normal((count, 2, 1)))[:, :, 0]
    return z, R, R_dep


def initialised_map(variant, truth, seed):
    """
    Return a map of ``fusion`` in which every landmark of ``truth`` is confirmed.

    Loaded as records (one observation's estimate per landmark, source ``warmup``):
    the tentative path takes new IDs one row at a time in Python, which would make
    the set-up of 100,000 landmarks the longest part of the run.
    """
    rng = np.random.default_rng(seed)
    ids = np.arange(len(truth))
    z, R, R_dep = observations(rng, truth, ids)
    fusion, _, sources = variant.partition('/')
    landmark_map = LandmarkMap(fusion, source_correlation='independent' if sources else 'unknown')
    landmark_map.load_records([
        {'id': i, 'mean': m, 'covariance': P, 'covariance_dependent': P_dep,
         'observations': 1, 'sources': ['warmup'], 'first_stamp_ns': 0, 'last_stamp_ns': 0}
        for i, m, P, P_dep in zip(ids.tolist(), z.tolist(), R.tolist(), R_dep.tolist())])
    return landmark_map


def throughput(landmarks, sources, batches, seed, variants=FUSION_METHODS):
    """
    Time ``update`` for every variant (``independent`` first) on the same rows.

    Returns
    -------
    dict
        ``fusion -> {'obs_per_s', 'cpu_obs_per_s', 'accepted'}``.

    """
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-500.0, 500.0, (landmarks, 2))
    names = np.array([f'robot{k}' for k in range(sources)])
    stream = []
    for _ in range(batches + 1):
        ids = rng.integers(0, landmarks, BATCH_ROWS)
        stream.append((ids, *observations(rng, truth, ids),
                       names[rng.integers(0, sources, BATCH_ROWS)].tolist()))
    maps = {fusion: initialised_map(fusion, truth, seed + 1) for fusion in variants}
    for landmark_map in maps.values():
        landmark_map.update(*stream[0])
    walls = {fusion: [] for fusion in variants}
    cpus = {fusion: [] for fusion in variants}
    accepted = dict.fromkeys(variants, 0)
    # Batch by batch, every method in turn (the order rotated): a slow spell of a
    # shared core then hits all methods alike, not one.
    for k, batch in enumerate(stream[1:]):
        turn = k % len(variants)
        for fusion in variants[turn:] + variants[:turn]:
            wall_start, cpu_start = time.perf_counter(), time.thread_time()
            result = maps[fusion].update(*batch)
            walls[fusion].append(time.perf_counter() - wall_start)
            cpus[fusion].append(time.thread_time() - cpu_start)
            accepted[fusion] += sum(result.accepted.values())
    rows = batches * BATCH_ROWS
    out = {}
    for fusion in variants:
        # Best batch: on a shared machine waiting for a core inflates the others.
        out[fusion] = {'obs_per_s': BATCH_ROWS / min(walls[fusion]),
                       'cpu_obs_per_s': BATCH_ROWS / min(cpus[fusion]),
                       'accepted': accepted[fusion] / rows,
                       # Against independent on the same batches: median of the ratios.
                       'ratio': float(np.median(np.array(cpus['independent'])
                                                / np.array(cpus[fusion]))),
                       'ratios': (np.array(cpus['independent']) / np.array(cpus[fusion])).tolist()}
    # Sources per landmark at the end (split CI's cost per row grows with them).
    sample = rng.choice(landmarks, min(landmarks, 500), replace=False).tolist()
    out['sources_per_landmark'] = float(np.mean([
        len(maps[variants[-1]].sources_of(i)) for i in sample]))
    return out


def memory_child(landmarks):
    """Build a split-CI map of ``landmarks`` landmarks (5 sources); print its memory as JSON."""
    import landmark_ros.fusion.landmark_map  # noqa: F401 - counted in the baseline
    baseline_kb = _common.vm_hwm_kb()
    rng = np.random.default_rng(1)
    truth = rng.uniform(-5000.0, 5000.0, (landmarks, 2))
    landmark_map = initialised_map('split_covariance_intersection', truth, 2)
    names = np.array([f'robot{k}' for k in range(5)])
    for _ in range(1):
        ids = rng.permutation(np.repeat(np.arange(landmarks), 3))
        for start in range(0, len(ids), 100_000):
            part = ids[start:start + 100_000]
            landmark_map.update(part, *observations(rng, truth, part),
                                names[rng.integers(0, 5, len(part))].tolist())
    print(json.dumps({'landmarks': len(landmark_map), 'hwm_kb': _common.vm_hwm_kb(),
                      'baseline_kb': baseline_kb,
                      'maxrss_kb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))


def memory(landmarks):
    """Return ``memory_child``'s figures, measured in a fresh interpreter."""
    done = subprocess.run([sys.executable, os.path.abspath(__file__), '--memory-child',
                           str(landmarks)], capture_output=True, text=True, check=True,
                          timeout=300)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    """Run the benchmark and print the report; return the figures."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--batches', type=int, default=4,
                        help='timed batches of 10,000 rows per method and size (default 4)')
    parser.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    parser.add_argument('--memory-child', type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.memory_child:
        memory_child(args.memory_child)
        return None
    started = time.perf_counter()
    numba = compiled.load()    # wait for the compiled fold (LANDMARK_ROS_NUMBA=0: numpy)
    mem = {n: memory(n) for n in MEMORY_LANDMARKS}
    host = _common.machine()
    lines = ['bench_map: LandmarkMap.update, batches of 10,000 rows into maps whose '
             'landmarks are all confirmed',
             f'machine: {host["cpu"]}; {host["cpu_count"]} CPUs; Python {host["python"]}; '
             f'numpy {host["numpy"]}; load average {os.getloadavg()[0]:.1f}; split-CI fold '
             f'{"compiled (numba)" if numba else "numpy"}', '']
    result = {}
    targets = {}
    by_size = {size: throughput(*size, args.batches, args.seed) for size in SIZES}
    for size in SIZES:     # after the methods' runs, which it would disturb
        by_size[size][INDEPENDENT_SOURCES] = throughput(
            *size, args.batches, args.seed, ('independent', INDEPENDENT_SOURCES))[
                INDEPENDENT_SOURCES]
    for (landmarks, sources), rates in by_size.items():
        lines.append(f'{landmarks} landmarks, {sources} sources:')
        for fusion in VARIANTS:
            rate = rates[fusion]
            ratio = rate['ratio']
            target = TARGETS.get(fusion)
            verdict = ''
            key = f'{SHORT[fusion]}_{landmarks}'
            if target is not None:
                targets[key] = ratio >= target
                verdict = (f'  target >= {target:.0%} of independent: '
                           f'{_common.verdict(targets[key])}')
            label = LABELS.get(fusion, fusion)
            lines.append(f'  {label:31s} {rate["obs_per_s"] / 1e3:8.1f} k obs/s '
                         f'(CPU time {rate["cpu_obs_per_s"] / 1e3:8.1f} k), '
                         f'{ratio:6.1%} of independent, accepted {rate["accepted"]:.1%}'
                         f'{verdict}')
            result[f'{key}_obs_per_s'] = rate['obs_per_s']
            result[f'{key}_ratio'] = ratio
        lines.append('  split CI / independent batch by batch: '
                     + ', '.join(f'{r:.0%}' for r in rates['split_covariance_intersection'][
                         'ratios'])
                     + f'; sources per landmark at the end: '
                     f'{rates["sources_per_landmark"]:.1f} (a row re-folds its landmark from '
                     'the changed source on)')
        lines.append('')
    lines.append('memory, split_covariance_intersection map, 5 sources, fresh interpreter:')
    for landmarks, figures in mem.items():
        growth = (figures['hwm_kb'] - figures['baseline_kb']) / 1024
        lines.append(f'  {figures["landmarks"]:7d} landmarks: peak RSS '
                     f'{figures["hwm_kb"] / 1024:.0f} MB (VmHWM; getrusage maxrss '
                     f'{figures["maxrss_kb"] / 1024:.0f} MB), '
                     f'{growth:.0f} MB over the interpreter with numpy and the package')
        result[f'peak_rss_split_ci_{landmarks}_landmarks_mb'] = figures['hwm_kb'] / 1024
        result[f'maxrss_split_ci_{landmarks}_landmarks_mb'] = figures['maxrss_kb'] / 1024
        result[f'map_growth_{landmarks}_landmarks_mb'] = growth
    seconds = time.perf_counter() - started
    lines.append('')
    lines.append(f'targets: {", ".join(f"{k} {_common.verdict(v)}" for k, v in targets.items())}'
                 f'; run time {seconds:.1f} s')
    lines.append('RESULT bench_map ' + ' '.join(f'{k}={v:.6g}' for k, v in result.items())
                 + f' pass={int(all(targets.values()))}')
    print('\n'.join(lines))
    sys.stdout.flush()
    return result


if __name__ == '__main__':
    main()
    sys.exit(0)
