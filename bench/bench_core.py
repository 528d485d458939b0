"""
Benchmark ``landmarks.landmark_to_world`` against a textbook per-observation loop.

Both place ``N`` random range-bearing observations in the world with their
first-order covariance, from the same inputs in the same run:

- vectorised: one call of ``landmark_ros.core.landmarks.landmark_to_world`` on all
  rows, best of several repeats on the full ``N``;
- loop: one observation at a time, written the way the chapter writes it: 3x1 column
  vectors, ``tcomp`` for pose composition, its Jacobians ``J1`` and ``J2`` as 3x3
  arrays, the polar-to-Cartesian Jacobian applied to ``R``, and
  ``J1 P J1^T + J2 Pz J2^T``. It is slow, so it is timed on a subset.

Two cases: full per-observation covariances (correlated pose covariance (N, 3, 3) and
sensor covariance (N, 2, 2)), and the common node case of one shared pose covariance
(3, 3) and one ``R`` (2, 2). Targets are printed with PASS/FAIL; the script exits 0
whatever the result. The last line is machine-readable::

    RESULT bench_core key=value ...

Run from the repository root with the package importable (``make bench`` does this
in the dev venv): ``python bench/bench_core.py [--n N] [--loop-n N]``.
"""

import argparse
import gc
import os
import platform
import sys
import time

import _common
from landmark_ros.core import landmarks
import numpy as np


TARGET_OBS_PER_S = 5e6
"""Vectorised throughput target [observations/s], per-observation covariances."""

TARGET_RATIO = 200.0
"""Target speed-up of the vectorised call over the loop."""

AGREEMENT_RTOL = 1e-9
"""Largest difference allowed between the two, relative to the largest magnitude."""


# --- The chapter's formulation: one observation at a time, 3x1 column vectors. -----

def tcomp(a, b):
    """
    Compose two poses given as 3x1 column vectors: ``a (+) b``.

    Parameters
    ----------
    a : ndarray, shape (3, 1)
        Pose of the frame ``b`` is given in.
    b : ndarray, shape (3, 1)
        Pose or point (third entry 0) relative to ``a``.

    Returns
    -------
    ndarray, shape (3, 1)
        ``b`` in the frame ``a`` is given in, angle wrapped to ``[-pi, pi)``.

    """
    angle = a[2, 0] + b[2, 0]
    angle = (angle + np.pi) % (2 * np.pi) - np.pi
    s = np.sin(a[2, 0])
    c = np.cos(a[2, 0])
    return np.array([[a[0, 0] + c * b[0, 0] - s * b[1, 0]],
                     [a[1, 0] + s * b[0, 0] + c * b[1, 0]],
                     [angle]])


def J1(a, b):
    """
    Return the Jacobian of ``tcomp(a, b)`` with respect to ``a``.

    Parameters
    ----------
    a : ndarray, shape (3, 1)
        First pose.
    b : ndarray, shape (3, 1)
        Second pose.

    Returns
    -------
    ndarray, shape (3, 3)
        The Jacobian.

    """
    s = np.sin(a[2, 0])
    c = np.cos(a[2, 0])
    return np.array([[1.0, 0.0, -s * b[0, 0] - c * b[1, 0]],
                     [0.0, 1.0, c * b[0, 0] - s * b[1, 0]],
                     [0.0, 0.0, 1.0]])


def J2(a, b):
    """
    Return the Jacobian of ``tcomp(a, b)`` with respect to ``b``.

    Parameters
    ----------
    a : ndarray, shape (3, 1)
        First pose.
    b : ndarray, shape (3, 1)
        Second pose (unused: the Jacobian depends on ``a`` only).

    Returns
    -------
    ndarray, shape (3, 3)
        The Jacobian.

    """
    s = np.sin(a[2, 0])
    c = np.cos(a[2, 0])
    return np.array([[c, -s, 0.0],
                     [s, c, 0.0],
                     [0.0, 0.0, 1.0]])


def landmark_to_world_loop(pose, P_pose, z, R):
    """
    Place observed landmarks in the world one at a time, as the chapter does.

    Parameters
    ----------
    pose : ndarray, shape (N, 3)
        Robot poses.
    P_pose : ndarray, shape (N, 3, 3) or (3, 3)
        Pose covariances, per observation or shared.
    z : ndarray, shape (N, 2)
        Observations ``(range, bearing)``.
    R : ndarray, shape (N, 2, 2) or (2, 2)
        Sensor covariances, per observation or shared.

    Returns
    -------
    m : ndarray, shape (N, 2)
        Landmarks in the world.
    P_m : ndarray, shape (N, 2, 2)
        Their covariances.

    """
    n = len(pose)
    m = np.empty((n, 2))
    P_m = np.empty((n, 2, 2))
    for i in range(n):
        x = pose[i].reshape(3, 1)
        P = P_pose if P_pose.ndim == 2 else P_pose[i]
        Rz = R if R.ndim == 2 else R[i]
        r, b = z[i, 0], z[i, 1]
        # Observation as a point in the robot frame, and its covariance.
        zc = np.array([[r * np.cos(b)], [r * np.sin(b)], [0.0]])
        Jp = np.array([[np.cos(b), -r * np.sin(b)],
                       [np.sin(b), r * np.cos(b)]])
        Pz = np.zeros((3, 3))
        Pz[0:2, 0:2] = Jp @ Rz @ Jp.T
        mw = tcomp(x, zc)
        A = J1(x, zc)
        B = J2(x, zc)
        Pm = A @ P @ A.T + B @ Pz @ B.T
        m[i] = mw[0:2, 0]
        P_m[i] = Pm[0:2, 0:2]
    return m, P_m


# --- Inputs, timing and report. ---------------------------------------------------

def make_inputs(n, seed):
    """
    Draw random observations with full, correlated covariances.

    Parameters
    ----------
    n : int
        Number of observations.
    seed : int
        Seed of ``numpy.random.default_rng``.

    Returns
    -------
    dict
        ``pose`` (n, 3), ``P_pose`` (n, 3, 3), ``z`` (n, 2), ``R`` (n, 2, 2), and the
        shared ``P_pose_shared`` (3, 3) and ``R_shared`` (2, 2).

    """
    rng = np.random.default_rng(seed)
    pose = np.column_stack([rng.uniform(-50.0, 50.0, (n, 2)),
                            rng.uniform(-np.pi, np.pi, n)])
    # Pose covariances A A^T + eps I with random A: full and correlated.
    A = rng.normal(size=(n, 3, 3)) * np.array([0.3, 0.3, 0.05])[:, None]
    P_pose = A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(3)
    z = np.column_stack([rng.uniform(0.5, 30.0, n), rng.uniform(-np.pi, np.pi, n)])
    sigma_r = rng.uniform(0.05, 0.5, n)
    sigma_b = rng.uniform(0.005, 0.05, n)
    rho = rng.uniform(-0.5, 0.5, n)
    R = np.empty((n, 2, 2))
    R[:, 0, 0] = sigma_r ** 2
    R[:, 1, 1] = sigma_b ** 2
    R[:, 0, 1] = R[:, 1, 0] = rho * sigma_r * sigma_b
    return {
        'pose': pose, 'P_pose': P_pose, 'z': z, 'R': R,
        'P_pose_shared': P_pose[0].copy(), 'R_shared': R[0].copy(),
    }


def best_time(function, repeats):
    """
    Return the best wall time of several calls and the result of the last one.

    Parameters
    ----------
    function : callable
        Called without arguments.
    repeats : int
        Number of timed calls (after one untimed warm-up call).

    Returns
    -------
    seconds : float
        Fastest call.
    result : object
        What ``function`` returned.

    """
    result = function()
    best = float('inf')
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for _ in range(repeats):
            start = time.perf_counter()
            result = function()
            best = min(best, time.perf_counter() - start)
    finally:
        if gc_was_enabled:
            gc.enable()
    return best, result


def machine():
    """
    Describe the machine the benchmark runs on.

    Returns
    -------
    dict
        ``cpu`` (model name), ``cpu_count``, ``usable_cpus``, ``platform``,
        ``python`` and ``numpy`` versions.

    """
    cpu = _common.cpu_model()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else None
    return {
        'cpu': cpu,
        'cpu_count': os.cpu_count(),
        'usable_cpus': usable,
        'platform': f'{platform.system()} {platform.machine()}',
        'python': platform.python_version(),
        'numpy': np.__version__,
    }


def run_case(pose, P_pose, z, R, loop_n, repeats, loop_repeats):
    """
    Time both implementations on the same inputs and compare their results.

    Parameters
    ----------
    pose : ndarray, shape (N, 3)
        Robot poses.
    P_pose : ndarray, shape (N, 3, 3) or (3, 3)
        Pose covariances.
    z : ndarray, shape (N, 2)
        Observations.
    R : ndarray, shape (N, 2, 2) or (2, 2)
        Sensor covariances.
    loop_n : int
        Rows the loop runs on (the first ``loop_n``).
    repeats : int
        Timed repeats of the vectorised call on all rows.
    loop_repeats : int
        Timed repeats of the loop.

    Returns
    -------
    dict
        ``vectorised_s``, ``loop_s`` (best times), ``vectorised_obs_per_s``,
        ``loop_obs_per_s``, ``ratio``, ``max_abs_diff_m``, ``max_abs_diff_P``,
        ``agree``.

    """
    n = len(pose)
    vec_s, (m, P_m) = best_time(lambda: landmarks.landmark_to_world(pose, P_pose, z, R),
                                repeats)

    def subset(a, single_ndim):
        return a if a.ndim == single_ndim else a[:loop_n]

    loop_args = (pose[:loop_n], subset(P_pose, 2), z[:loop_n], subset(R, 2))
    loop_s, (m_loop, P_loop) = best_time(lambda: landmark_to_world_loop(*loop_args),
                                         loop_repeats)
    diff_m = float(np.max(np.abs(m[:loop_n] - m_loop)))
    diff_P = float(np.max(np.abs(P_m[:loop_n] - P_loop)))
    scale = max(1.0, float(np.max(np.abs(m_loop))), float(np.max(np.abs(P_loop))))
    vec_rate = n / vec_s
    loop_rate = loop_n / loop_s
    return {
        'vectorised_s': vec_s,
        'loop_s': loop_s,
        'vectorised_obs_per_s': vec_rate,
        'loop_obs_per_s': loop_rate,
        'ratio': vec_rate / loop_rate,
        'max_abs_diff_m': diff_m,
        'max_abs_diff_P': diff_P,
        'agree': max(diff_m, diff_P) <= AGREEMENT_RTOL * scale,
    }


def report_case(title, case, n, loop_n, repeats, loop_repeats, targets):
    """
    Return the report lines of one case.

    Parameters
    ----------
    title : str
        Heading.
    case : dict
        From ``run_case``.
    n : int
        Rows of the vectorised call.
    loop_n : int
        Rows of the loop.
    repeats : int
        Timed repeats of the vectorised call.
    loop_repeats : int
        Timed repeats of the loop.
    targets : bool
        Whether to print the targets next to the figures.

    Returns
    -------
    list of str
        The lines.

    """
    vec, loop = case['vectorised_obs_per_s'], case['loop_obs_per_s']
    vec_target = (f'   target >= {TARGET_OBS_PER_S:.3g} obs/s: '
                  f'{_common.verdict(vec >= TARGET_OBS_PER_S)}') if targets else ''
    ratio_target = (f'   target >= {TARGET_RATIO:g}x: '
                    f'{_common.verdict(case["ratio"] >= TARGET_RATIO)}') if targets else ''
    return [
        title,
        f'  vectorised  N = {n:>7}, best of {repeats:>2}: {case["vectorised_s"] * 1e3:9.3f} ms'
        f'  {vec:12.4g} obs/s  ({1e9 / vec:7.1f} ns/obs){vec_target}',
        f'  loop        N = {loop_n:>7}, best of {loop_repeats:>2}: '
        f'{case["loop_s"] * 1e3:9.3f} ms  {loop:12.4g} obs/s  ({1e6 / loop:7.2f} us/obs)',
        f'  ratio       {case["ratio"]:.1f}x{ratio_target}',
        f'  agreement on the {loop_n} loop rows: max |diff| m {case["max_abs_diff_m"]:.2e}, '
        f'P_m {case["max_abs_diff_P"]:.2e}: {_common.verdict(case["agree"])}',
    ]


def main(argv=None):
    """
    Run the benchmark, print the report and return the figures.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments without the program name; ``None`` reads
        ``sys.argv``.

    Returns
    -------
    dict
        ``machine`` (see ``machine``), ``n``, ``loop_n``, ``per_observation`` and
        ``shared`` (see ``run_case``), ``targets`` (name to bool) and ``seconds``
        (total run time).

    """
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--n', type=int, default=100_000,
                        help='observations for the vectorised call (default 100000)')
    parser.add_argument('--loop-n', type=int, default=5_000,
                        help='observations for the loop, a prefix of the N (default 5000)')
    parser.add_argument('--repeats', type=int, default=30,
                        help='timed repeats of the vectorised call (default 30)')
    parser.add_argument('--loop-repeats', type=int, default=5,
                        help='timed repeats of the loop (default 5)')
    parser.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    args = parser.parse_args(argv)
    loop_n = min(args.loop_n, args.n)

    started = time.perf_counter()
    host = machine()
    data = make_inputs(args.n, args.seed)
    full = run_case(data['pose'], data['P_pose'], data['z'], data['R'],
                    loop_n, args.repeats, args.loop_repeats)
    shared = run_case(data['pose'], data['P_pose_shared'], data['z'], data['R_shared'],
                      loop_n, args.repeats, args.loop_repeats)
    seconds = time.perf_counter() - started
    targets = {
        'vectorised_obs_per_s': full['vectorised_obs_per_s'] >= TARGET_OBS_PER_S,
        'ratio': full['ratio'] >= TARGET_RATIO,
        'agree': full['agree'] and shared['agree'],
    }

    lines = [
        f'bench_core: landmarks.landmark_to_world, N = {args.n} random observations '
        f'(seed {args.seed})',
        f'machine: {host["cpu"]}; {host["cpu_count"]} CPUs ({host["usable_cpus"]} usable); '
        f'{host["platform"]}; Python {host["python"]}; numpy {host["numpy"]}',
        '',
        *report_case('per-observation covariances: P_pose (N, 3, 3) full, R (N, 2, 2) full',
                     full, args.n, loop_n, args.repeats, args.loop_repeats, True),
        '',
        *report_case('shared covariances (node case): P_pose (3, 3), R (2, 2)',
                     shared, args.n, loop_n, args.repeats, args.loop_repeats, False),
        '',
        f'targets: {", ".join(f"{k} {_common.verdict(v)}" for k, v in targets.items())}; '
        f'run time {seconds:.1f} s',
        'RESULT bench_core'
        f' n={args.n} loop_n={loop_n}'
        f' vectorised_obs_per_s={full["vectorised_obs_per_s"]:.6g}'
        f' loop_obs_per_s={full["loop_obs_per_s"]:.6g}'
        f' ratio={full["ratio"]:.6g}'
        f' shared_vectorised_obs_per_s={shared["vectorised_obs_per_s"]:.6g}'
        f' shared_loop_obs_per_s={shared["loop_obs_per_s"]:.6g}'
        f' shared_ratio={shared["ratio"]:.6g}'
        f' max_abs_diff={max(full["max_abs_diff_m"], full["max_abs_diff_P"]):.3g}'
        f' cpus={host["cpu_count"]} numpy={host["numpy"]}'
        f' pass={int(all(targets.values()))}',
    ]
    print('\n'.join(lines))
    sys.stdout.flush()
    return {
        'machine': host,
        'n': args.n,
        'loop_n': loop_n,
        'per_observation': full,
        'shared': shared,
        'targets': targets,
        'seconds': seconds,
    }


if __name__ == '__main__':
    main()
    sys.exit(0)
