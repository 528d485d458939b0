"""
Textbook exercises on uncertain landmarks, solved with ``landmark_ros.core``.

Run ``python -m landmark_ros.eval.exercises [--plot FILE.png]``. Every number printed is
computed here by the core (nothing is hard-coded), to first order unless stated:

1. Landmark ``m1`` observed by robot R1 whose pose is exactly known.
2. The same landmark when R1's pose is uncertain.
3. Relative pose of R2 seen from R1, by ``between`` and by ``composition``.
4. Predicted observation of ``m1`` from R2, with a reproduction of the textbook's
   (wrong) figure, the reason it is wrong, and a Monte Carlo check.
5. Landmark ``m2`` observed by R2 and its fusion with ``m1``.

``--plot`` draws the chapter-style figure; it needs matplotlib (the optional extra
``landmark_ros[plot]``).
"""

import argparse
from pathlib import Path
import sys

from landmark_ros.core import gaussian, landmarks, pose2, sensors
from landmark_ros.eval import plotting
import numpy as np


MC_SAMPLES = 200_000
"""Monte Carlo samples for the check of exercise 4."""

MC_SEED = 1
"""Seed of the Monte Carlo generator, so the report is reproducible."""

MC_SMALL_SCALE = 0.01
"""Covariance scale of the second Monte Carlo run (near-linear regime)."""

EXIT_NO_MATPLOTLIB = 2
"""Exit status of ``main`` when ``--plot`` is asked for without matplotlib."""


def sandwich(J, P):
    """Return ``J P J^T``, symmetrised: J (m, n) or (N, m, n), P (n, n) or (N, n, n)."""
    out = J @ P @ np.swapaxes(J, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def inputs():
    """
    Return the data of the exercises.

    Returns
    -------
    dict
        ``p1``, ``P1``, ``z1`` (robot R1, its covariance, its observation of m1),
        ``p2``, ``P2``, ``z2`` (robot R2, its covariance, its observation of m2) and
        ``R`` (sensor noise of both observations), all float64 arrays.

    """
    return {
        'p1': np.array([1.0, 2.0, 0.5]),
        'P1': np.diag([0.08, 0.6, 0.02]),
        'z1': np.array([4.0, 0.7]),
        'p2': np.array([6.0, 4.0, 2.1]),
        'P2': np.diag([0.20, 0.09, 0.03]),
        'z2': np.array([4.0, 0.3]),
        'R': np.diag([0.25, 0.04]),
    }


def textbook_observation_covariance(p2, P2, m1, P_m1):
    """
    Reproduce the textbook's covariance of the predicted observation of ``m1``.

    The textbook expresses ``m1`` in the robot's frame, ``q = (-)p2 (+) m1``, with
    ``P_q`` from the Jacobians of the point transform with respect to the inverted
    pose and to ``m1``. It then evaluates the polar Jacobian at the world-frame
    difference ``m1 - (x2, y2)`` instead of at ``q``. Both vectors have the same
    length but differ by a rotation through the robot's heading, so the result is
    wrong unless the heading is zero. Evaluated at ``q``, the same chain gives the
    correct ``P_z``.

    Parameters
    ----------
    p2 : ndarray, shape (3,)
        Robot pose in the world.
    P2 : ndarray, shape (3, 3)
        Its covariance.
    m1 : ndarray, shape (2,)
        Landmark in the world.
    P_m1 : ndarray, shape (2, 2)
        Its covariance.

    Returns
    -------
    dict
        ``q`` and ``P_q`` (``m1`` in the robot frame and its covariance), ``d_world``
        (``m1 - (x2, y2)``), ``P_z_textbook`` (polar Jacobian at ``d_world``) and
        ``P_z_at_q`` (polar Jacobian at ``q``, the correct first-order result).

    """
    p2_inv = pose2.inverse(p2)
    P2_inv = sandwich(pose2.inverse_jacobian(p2), P2)
    q = pose2.transform_point(p2_inv, m1)
    J_q_inv, J_q_m = pose2.transform_point_jacobians(p2_inv, m1)
    P_q = sandwich(J_q_inv, P2_inv) + sandwich(J_q_m, P_m1)
    d_world = m1 - p2[:2]
    return {
        'q': q,
        'P_q': P_q,
        'd_world': d_world,
        'P_z_textbook': sandwich(sensors.cartesian_to_polar_jacobian(d_world), P_q),
        'P_z_at_q': sandwich(sensors.cartesian_to_polar_jacobian(q), P_q),
    }


def monte_carlo_observation(p2, P2, m1, P_m1, samples=MC_SAMPLES, seed=MC_SEED, scale=1.0):
    """
    Estimate the mean and covariance of ``observe(p2, m1)`` by sampling.

    Pose and landmark are drawn independently from ``N(p2, scale P2)`` and
    ``N(m1, scale P_m1)`` and pushed through ``sensors.observe`` in one batch.

    Parameters
    ----------
    p2 : ndarray, shape (3,)
        Robot pose in the world.
    P2 : ndarray, shape (3, 3)
        Its covariance.
    m1 : ndarray, shape (2,)
        Landmark in the world.
    P_m1 : ndarray, shape (2, 2)
        Its covariance.
    samples : int
        Number of samples.
    seed : int
        Seed of ``numpy.random.default_rng``.
    scale : float
        Factor applied to both covariances.

    Returns
    -------
    dict
        ``samples``, ``seed``, ``scale``, ``z_mean`` (2,) and ``P_z`` (2, 2), the sample
        covariance (not divided by ``scale``).

    """
    rng = np.random.default_rng(seed)
    poses = rng.multivariate_normal(p2, scale * P2, size=samples)
    points = rng.multivariate_normal(m1, scale * P_m1, size=samples)
    z = sensors.observe(poses, points)
    return {
        'samples': samples,
        'seed': seed,
        'scale': scale,
        'z_mean': z.mean(axis=0),
        'P_z': np.cov(z, rowvar=False),
    }


def solve(mc_samples=MC_SAMPLES, seed=MC_SEED):
    """
    Solve the five exercises.

    Parameters
    ----------
    mc_samples : int
        Samples of each Monte Carlo run of exercise 4.
    seed : int
        Seed of the Monte Carlo runs.

    Returns
    -------
    dict
        ``inputs`` (see ``inputs``) and one dict per exercise, ``case1`` to ``case5``:

        - ``case1``: ``m1``, ``P_m1`` with R1's pose exact;
        - ``case2``: ``m1``, ``P_m1`` with ``P1``;
        - ``case3``: ``between`` and ``composition``, each ``(p12, P12)``, and
          ``max_abs_difference`` between them;
        - ``case4``: ``z``, ``P_z`` (correct), the entries of
          ``textbook_observation_covariance``, ``heading_offset`` (angle from
          ``d_world`` to ``q``), ``mc`` and ``mc_small`` (``monte_carlo_observation``
          at scale 1 and ``MC_SMALL_SCALE``);
        - ``case5``: ``m2``, ``P_m2``, ``m_fused``, ``P_fused``.

    """
    data = inputs()
    p1, P1, z1 = data['p1'], data['P1'], data['z1']
    p2, P2, z2, R = data['p2'], data['P2'], data['z2'], data['R']

    m1_exact, P_m1_exact = landmarks.landmark_to_world(p1, np.zeros((3, 3)), z1, R)
    m1, P_m1 = landmarks.landmark_to_world(p1, P1, z1, R)

    between = landmarks.relative_pose(p1, P1, p2, P2, method='between')
    composition = landmarks.relative_pose(p1, P1, p2, P2, method='composition')
    relative_difference = max(
        float(np.max(np.abs(a - b))) for a, b in zip(between, composition))

    z, P_z = landmarks.predict_observation(p2, P2, m1, P_m1)
    textbook = textbook_observation_covariance(p2, P2, m1, P_m1)
    q, d_world = textbook['q'], textbook['d_world']
    heading_offset = float(pose2.wrap_angle(
        np.arctan2(q[1], q[0]) - np.arctan2(d_world[1], d_world[0])))
    mc = monte_carlo_observation(p2, P2, m1, P_m1, mc_samples, seed)
    mc_small = monte_carlo_observation(p2, P2, m1, P_m1, mc_samples, seed, MC_SMALL_SCALE)

    m2, P_m2 = landmarks.landmark_to_world(p2, P2, z2, R)
    m_fused, P_fused = gaussian.fuse(m1, P_m1, m2, P_m2)

    return {
        'inputs': data,
        'case1': {'m1': m1_exact, 'P_m1': P_m1_exact},
        'case2': {'m1': m1, 'P_m1': P_m1},
        'case3': {
            'between': between,
            'composition': composition,
            'max_abs_difference': relative_difference,
        },
        'case4': {
            'z': z,
            'P_z': P_z,
            **textbook,
            'heading_offset': heading_offset,
            'mc': mc,
            'mc_small': mc_small,
        },
        'case5': {'m2': m2, 'P_m2': P_m2, 'm_fused': m_fused, 'P_fused': P_fused},
    }


def _fmt(array, indent=0):
    """
    Format a vector or matrix with 8 decimals.

    Parameters
    ----------
    array : array_like
        Vector or matrix.
    indent : int
        Spaces before every line but the first.

    Returns
    -------
    str
        The formatted array.

    """
    text = np.array2string(
        np.asarray(array, dtype=np.float64) + 0.0, separator=', ',
        formatter={'float_kind': lambda v: f'{v: .8f}'})
    return text.replace('\n', '\n' + ' ' * indent)


def _line(name, array, width=14):
    """
    Return ``name = array`` with continuation lines aligned under the array.

    Parameters
    ----------
    name : str
        Label.
    array : array_like
        Vector or matrix.
    width : int
        Width of the label column.

    Returns
    -------
    str
        One or more lines, without a trailing newline.

    """
    label = f'    {name:<{width}} = '
    return label + _fmt(array, len(label))


def _mc_check(mc, P_z, P_z_textbook):
    """
    Compare a Monte Carlo covariance with the first-order one and the textbook's.

    Parameters
    ----------
    mc : dict
        From ``monte_carlo_observation``.
    P_z : ndarray, shape (2, 2)
        Correct first-order covariance.
    P_z_textbook : ndarray, shape (2, 2)
        The textbook's covariance.

    Returns
    -------
    dict
        ``P_z`` (the Monte Carlo covariance divided by its scale),
        ``relative_difference`` (largest ``|MC - P_z|_ij / sqrt(P_z_ii P_z_jj)``),
        ``closer_to_correct`` (every entry nearer ``P_z`` than ``P_z_textbook``) and
        ``correlation`` (correlation coefficients of MC, correct and textbook).

    """
    P_mc = mc['P_z'] / mc['scale']
    norm = np.sqrt(np.outer(np.diag(P_z), np.diag(P_z)))

    def correlation(P):
        return float(P[0, 1] / np.sqrt(P[0, 0] * P[1, 1]))

    return {
        'P_z': P_mc,
        'relative_difference': float(np.max(np.abs(P_mc - P_z) / norm)),
        'closer_to_correct': bool(np.all(np.abs(P_mc - P_z) < np.abs(P_mc - P_z_textbook))),
        'correlation': tuple(correlation(P) for P in (P_mc, P_z, P_z_textbook)),
    }


def format_report(results):
    """
    Format the results of ``solve`` as text.

    Parameters
    ----------
    results : dict
        From ``solve``.

    Returns
    -------
    str
        The report, matrices with 8 decimals, ending with a newline.

    """
    data = results['inputs']
    c1, c2, c3 = results['case1'], results['case2'], results['case3']
    c4, c5 = results['case4'], results['case5']
    theta2 = float(data['p2'][2])
    out = [
        'landmark_ros textbook exercises (first-order propagation by landmark_ros.core)',
        '',
        'Inputs',
        _line('p1', data['p1']), _line('P1', data['P1']), _line('z1', data['z1']),
        _line('p2', data['p2']), _line('P2', data['P2']), _line('z2', data['z2']),
        _line('R', data['R']),
        '',
        '1. Landmark m1 observed by R1, pose exact (P1 = 0): landmark_to_world',
        _line('m1', c1['m1']), _line('P_m1', c1['P_m1']),
        '',
        '2. Landmark m1 observed by R1 with pose covariance P1: landmark_to_world',
        _line('m1', c2['m1']), _line('P_m1', c2['P_m1']),
        '',
        '3. Pose of R2 relative to R1, (-)p1 (+) p2: relative_pose',
    ]
    for method in ('between', 'composition'):
        p12, P12 = c3[method]
        out += [f'  method={method!r}', _line('p12', p12), _line('P12', P12)]
    out += [
        f'  The two methods agree: max |difference| = {c3["max_abs_difference"]:.3e}',
        '',
        '4. Predicted observation of m1 (case 2) from R2: predict_observation',
        _line('z', c4['z']), _line('P_z', c4['P_z']),
        '  The textbook prints a different P_z. Reproduced:',
        _line('P_z (textbook)', c4['P_z_textbook']),
        "  It expresses m1 in R2's frame, q = (-)p2 (+) m1, with P_q from the",
        '  transform_point Jacobians of the inverted pose and of m1:',
        _line('q', c4['q']), _line('P_q', c4['P_q']),
        '  but evaluates the polar Jacobian (cartesian_to_polar_jacobian) at the',
        '  world-frame difference instead of at q:',
        _line('m1 - (x2, y2)', c4['d_world']),
        f'  Same length, but rotated by {c4["heading_offset"]:.8f} rad = minus R2\'s '
        f'heading {theta2:.8f},',
        '  so the rows of the Jacobian point the wrong way and P_z is wrong. With the',
        '  Jacobian taken at q the same chain gives the correct P_z:',
        _line('P_z (J at q)', c4['P_z_at_q']),
        '  Difference from predict_observation: max |difference| = '
        f'{np.max(np.abs(c4["P_z_at_q"] - c4["P_z"])):.3e}',
    ]
    for key in ('mc', 'mc_small'):
        mc = c4[key]
        check = _mc_check(mc, c4['P_z'], c4['P_z_textbook'])
        scaled = mc['scale'] != 1.0
        out += [
            ('  Monte Carlo, both covariances scaled by s = {:g}'.format(mc['scale'])
             if scaled else '  Monte Carlo check') + ':',
            f'    {mc["samples"]} samples, seed {mc["seed"]}, vectorised through '
            'sensors.observe',
            _line('mean z (MC)', mc['z_mean']),
            _line('P_z (MC) / s' if scaled else 'P_z (MC)', check['P_z']),
            '    largest |MC - P_z|_ij / sqrt(P_z_ii P_z_jj) = '
            f'{check["relative_difference"]:.4f}',
            "    every entry closer to the correct P_z than to the textbook's: "
            + ('yes' if check['closer_to_correct'] else 'NO'),
            '    range-bearing correlation: MC {:+.4f}, correct {:+.4f}, textbook {:+.4f}'
            .format(*check['correlation']),
        ]
    out += [
        '  At full scale the Monte Carlo differs from any first-order figure by the',
        '  linearisation error (position sigma ~1 m at 4 m range); with the covariances',
        '  scaled down that error vanishes and Monte Carlo matches the correct P_z.',
        '',
        '5. Landmark m2 observed by R2, and fusion with m1: landmark_to_world, fuse',
        _line('m2', c5['m2']), _line('P_m2', c5['P_m2']),
        _line('m (fused)', c5['m_fused']), _line('P_m (fused)', c5['P_fused']),
    ]
    return '\n'.join(out) + '\n'


def plot(results, path):
    """
    Draw the chapter-style figure of the exercises into an image file.

    Robots are oriented triangles with 1-sigma ellipses of their (x, y) covariance;
    the observation rays, the landmark estimates m1 (case 2) and m2 with their
    1-sigma ellipses, and the fused estimate are drawn on equal axes.

    Parameters
    ----------
    results : dict
        From ``solve``.
    path : str or pathlib.Path
        Output file; its suffix selects the format (e.g. ``.png``).

    Raises
    ------
    landmark_ros.eval.plotting.PlotUnavailableError
        If matplotlib is not installed.

    """
    data, c2, c4, c5 = (results[k] for k in ('inputs', 'case2', 'case4', 'case5'))
    fig, ax = plotting.new_figure()
    robots = (('R1', data['p1'], data['P1'], 'tab:blue'),
              ('R2', data['p2'], data['P2'], 'tab:orange'))
    for name, pose, P, colour in robots:
        plotting.draw_robot(ax, pose, P, colour=colour, label=f'robot {name}, 1-sigma (x, y)')

    rays = ((data['p1'], c2['m1'], 'tab:blue', '-', 'observation z1 (R1 to m1)'),
            (data['p2'], c5['m2'], 'tab:orange', '-', 'observation z2 (R2 to m2)'),
            (data['p2'], c2['m1'], 'tab:gray', ':',
             'predicted observation of m1 from R2'))
    for pose, m, colour, style, label in rays:
        ax.plot([pose[0], m[0]], [pose[1], m[1]], color=colour, linestyle=style,
                linewidth=1.0, label=label)

    estimates = ((c2['m1'], c2['P_m1'], 'tab:green', 'o', 'm1 from R1'),
                 (c5['m2'], c5['P_m2'], 'tab:purple', 's', 'm2 from R2'),
                 (c5['m_fused'], c5['P_fused'], 'tab:red', '*', 'fused m1, m2'))
    for m, P, colour, marker, label in estimates:
        plotting.draw_ellipse(ax, m, P, color=colour, linewidth=1.5)
        ax.plot(m[0], m[1], linestyle='none', marker=marker, markersize=9, color=colour,
                label=f'{label}, 1-sigma')

    z = c4['z']
    plotting.finish(fig, ax, path, 'Landmark seen by two uncertain robots, fused\n'
                    f'(R2 predicts m1 at range {z[0]:.2f} m, bearing {z[1]:.2f} rad)')


def main(argv=None):
    """
    Print the solutions and optionally draw the figure.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments without the program name; ``None`` reads
        ``sys.argv``.

    Returns
    -------
    int
        0 on success, ``EXIT_NO_MATPLOTLIB`` if ``--plot`` was given without
        matplotlib.

    """
    parser = argparse.ArgumentParser(
        prog='python -m landmark_ros.eval.exercises',
        description='Solve the textbook exercises on uncertain landmarks with '
                    'landmark_ros.core and print the results.')
    parser.add_argument(
        '--plot', metavar='FILE.png', type=Path,
        help='also draw the chapter-style figure into FILE.png (needs matplotlib, '
             'the extra landmark_ros[plot])')
    args = parser.parse_args(argv)

    results = solve()
    sys.stdout.write(format_report(results))
    if args.plot is not None:
        try:
            plot(results, args.plot)
        except plotting.PlotUnavailableError as exc:
            print(f'error: {exc}', file=sys.stderr)
            return EXIT_NO_MATPLOTLIB
        print(f'Figure written to {args.plot}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
