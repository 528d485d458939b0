"""
Cost of a partial view's update: split CI against split CI with the bias as a consider state.

``core.partial.update`` (split CI) and ``core.partial.update_consider`` on the same range
views, interleaved in one run: one view per call (how the fuser updates a placed
landmark) and batches of 1,024 (one landmark per view). Prints microseconds per view,
the ratio, a PASS/FAIL per target and a last line ``RESULT bench_partial key=value ...``.

Target: the consider update costs at most twice split CI's per view, one view per call.

Usage: ``python bench/bench_partial.py [--calls N] [--blocks B]``.
"""

import argparse
import statistics

import _common
from landmark_ros.core.partial import RANGE, update, update_consider, Views
import numpy as np

TARGET_RATIO = 2.0
"""Most the consider update may cost per view, one view per call, against split CI's."""


def views(count, seed):
    """Return range views 1.5 to 4 m from landmarks at the origin, with a range scale."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(-np.pi, np.pi, count)
    r = rng.uniform(1.5, 4.0, count)
    heading = angle + np.pi + rng.uniform(-0.4, 0.4, count)
    s = np.column_stack([r * np.cos(angle), r * np.sin(angle), heading])
    P_s = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-5]), (count, 3, 3))
    return Views(RANGE, s, P_s, r + rng.normal(0, 0.02, count), 4e-4, 1e-3,
                 (0.04, 0.0, -0.46), 0.6)


def cases(count, seed):
    """Return the arguments of both updates for ``count`` (landmark, view) pairs."""
    rng = np.random.default_rng(seed + 1)
    m = rng.normal(0, 0.05, (count, 2))
    P_dep = np.broadcast_to(np.eye(2) * 1e-3, (count, 2, 2))
    P = P_dep + np.eye(2) * 2e-3
    c = rng.normal(0, 0.01, (count, 2))
    return m, P, views(count, seed), P_dep, c


def per_view_us(function, calls, blocks, views_per_call):
    """Return the median CPU microseconds per view of ``function(i)``."""
    _, cpu = _common.time_per_call(function, calls, blocks)
    return statistics.median(cpu) * 1e6 / views_per_call


def measure(calls, blocks):
    """Return microseconds per view of both updates, one view per call and batched."""
    m, P, v, P_dep, c = cases(256, 0)
    single = [(m[i], P[i], v[i], P_dep[i], c[i]) for i in range(256)]
    split = 'split_covariance_intersection'
    out = {
        'split_ci_single_us': per_view_us(
            lambda i: update(*single[i % 256][:4], split), calls, blocks, 1),
        'consider_single_us': per_view_us(
            lambda i: update_consider(*single[i % 256]), calls, blocks, 1)}
    m, P, v, P_dep, c = cases(1024, 1)
    batch_calls = max(4, calls // 64)
    out['split_ci_batch_us'] = per_view_us(lambda i: update(m, P, v, P_dep, split),
                                           batch_calls, blocks, 1024)
    out['consider_batch_us'] = per_view_us(lambda i: update_consider(m, P, v, P_dep, c),
                                           batch_calls, blocks, 1024)
    out['consider_ratio_single'] = out['consider_single_us'] / out['split_ci_single_us']
    out['consider_ratio_batch'] = out['consider_batch_us'] / out['split_ci_batch_us']
    return out


def main(argv=None):
    """Run the benchmark and print its report."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--calls', type=int, default=2000)
    parser.add_argument('--blocks', type=int, default=10)
    args = parser.parse_args(argv)
    print(_common.machine_line(_common.machine()))
    result = measure(args.calls, args.blocks)
    print(f"one view per call: split CI {result['split_ci_single_us']:.1f} us, consider "
          f"{result['consider_single_us']:.1f} us ({result['consider_ratio_single']:.2f}x)")
    print(f"batches of 1024:   split CI {result['split_ci_batch_us']:.2f} us/view, consider "
          f"{result['consider_batch_us']:.2f} us/view ({result['consider_ratio_batch']:.2f}x)")
    ok = result['consider_ratio_single'] <= TARGET_RATIO
    print(f'target consider <= {TARGET_RATIO:g}x split CI per view: {_common.verdict(ok)}')
    print('RESULT bench_partial ' + ' '.join(f'{k}={v:.6g}' for k, v in result.items()))
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
