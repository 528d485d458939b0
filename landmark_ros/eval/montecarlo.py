"""
Monte Carlo consistency of the three fusion methods in the simulator (ROS-free).

``python -m landmark_ros.eval.montecarlo [--seeds 50] [--duration 20] [--scenario NAME]
[--fusion METHOD]`` runs the simulator
(``landmark_ros.sim.simulation``) for many seeds and drives the pipeline the nodes run
with it: one ``observer.Observer`` per robot (its noise parameters are the
simulator's), fed with the poses and observation messages in the order and with the
stamps the ``landmark_sim`` node publishes them, and one ``fuser.Fuser`` per
fusion method, fed with every observer's landmark batches and fused every
``update_period_s`` of simulated time, as the ``landmark_fuser`` node's timer does.
It then averages the NEES of the fused landmarks, per seed and over all seeds. A
consistent estimator's average NEES is 2. Within one seed the landmarks share the
robots' pose errors and biases, so their errors are correlated and the chi-square
interval of ``2 K`` degrees of freedom (for ``K`` independent landmarks, printed for
reference) is too narrow; the verdict therefore treats the seeds as the independent
samples: the mean of the per-seed average NEES and its 95 % confidence interval (1.96
standard errors).

Six scenarios:

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
range, bearing, mixed
    White noise as ``white``, with every robot range-only, every robot bearing-only,
    or one robot of each kind (``SimConfig.sensor_kinds``): the observers send the
    partial rows as views (``partial_observations``), the fusers place the landmarks
    from them (``fuser.partial``, delayed initialisation) and update them one view
    at a time. The plain EKF (``independent``) is the exact model to first order and
    must be inside the interval; CI and split CI must not be above it.
shared_frame
    The team's map frame is off by a rigid transform drawn once per run (5 cm, 10 mrad:
    the white pose error's budget, shared instead of drawn per observation; no white
    pose error), ``sim.frame_error``: every robot's observation of a landmark carries
    the same error, within and across robots, and its covariance is what the observers
    propagate as the dependent part. Split CI bounds the dependent parts as CI does
    (scalar weights, valid for any correlation), which is tight but not exact when they
    are one and the same error: it must not be above the interval; ``independent``
    averages the shared error down and must be over-confident (above); CI must not be
    above it.

    Every landmark of a run shares the one frame draw, so the per-seed average NEES
    varies a lot from seed to seed (a quadratic form in three normal variables,
    skewed). The frame-averaged NEES (``frame_averaged_nees``) removes that variance:
    the fused error is ``m - l = e(l) + n`` with ``e(l)`` the frame error at ``l``
    (``FrameError.point_error``) and ``n`` the rest; as ``e`` is independent of ``n``
    with covariance ``D(l)`` (``FrameError.point_covariance``), ``E[NEES] =
    tr(P^-1 D(l)) + E[n^T P^-1 n]``, and ``tr(P^-1 D(l)) + n^T P^-1 n`` has the same
    expectation as the NEES and a far smaller spread. It is printed next to the
    plain figure (the verdict stays on the plain one).
"""

import argparse
from dataclasses import replace
import sys
import time

from landmark_ros.eval.metrics import anees_interval, evaluate
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.fusion.landmark_map import FUSION_METHODS
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.sim import simulation
import numpy as np

SCENARIOS = {
    'white': {},
    'biased': {'range_bias_stddev': 0.05, 'bearing_bias_stddev': 0.01},
    'range': {'sensor_kinds': ('range',)},
    'bearing': {'sensor_kinds': ('bearing',)},
    'mixed': {'sensor_kinds': ('rb', 'range', 'bearing')},
    'shared_frame': {'frame_xy_stddev': 0.05, 'frame_yaw_stddev': 0.01,
                     'pose_xy_stddev': 0.0, 'pose_yaw_stddev': 0.0},
}
"""Changes to the simulator defaults per scenario."""

EXPECTED = {
    ('white', 'independent'): 'inside',
    ('white', 'covariance_intersection'): 'not above',
    ('white', 'split_covariance_intersection'): 'not above',
    ('biased', 'independent'): 'above',
    ('biased', 'covariance_intersection'): 'not above',
    ('biased', 'split_covariance_intersection'): 'not above',
    **{(kind, method): 'inside' if method == 'independent' else 'not above'
       for kind in ('range', 'bearing', 'mixed') for method in FUSION_METHODS},
    ('shared_frame', 'independent'): 'above',
    ('shared_frame', 'covariance_intersection'): 'not above',
    ('shared_frame', 'split_covariance_intersection'): 'not above',
}
"""What theory says of the pooled average NEES, per scenario and method."""


START_NS = 1_000_000_000
"""Clock time of simulated time zero [ns]: the node stamps ``start + simulated time``,
and the observer takes no zero stamp."""


def observer_config(sim_config):
    """
    Return the observers' parameters: the simulator's noise model, defaults otherwise.

    Parameters
    ----------
    sim_config : landmark_ros.sim.simulation.SimConfig
        The simulator's parameters: noise and bias standard deviations.

    Returns
    -------
    ObserverConfig

    """
    return ObserverConfig(range_stddev=sim_config.range_stddev,
                          bearing_stddev=sim_config.bearing_stddev,
                          range_bias_stddev=sim_config.range_bias_stddev,
                          bearing_bias_stddev=sim_config.bearing_bias_stddev)


def fuse_simulation(sim, methods=FUSION_METHODS, gate_probability=0.999, configs=None,
                    hide_ids=False, measurements=None):
    """
    Run a simulation through one ``Observer`` per robot and one ``Fuser`` per method.

    Poses and observation messages go to the observers in the order ``landmark_sim``
    publishes them (by stamp; at equal progress an observation before the pose that
    follows it; robots in turn), stamped ``START_NS`` plus the simulated time; the
    observers' clock is the stamp of what they are given. Every landmark batch an
    observer returns goes to every fuser at once; the fusers fuse what is queued
    every ``update_period_s`` of simulated time and at the end.

    Parameters
    ----------
    sim : landmark_ros.sim.simulation.Simulation
        A simulation with a finite ``duration_s``; the last observation before it is
        placed with the pose after it.
    methods : sequence of str
        Fusion methods.
    gate_probability : float
        The fusers' gate.
    configs : dict of str to FuserConfig, optional
        Instead of ``methods``: one fuser per entry, ``name -> its parameters``.
    hide_ids : bool
        Send the observation messages without their ``id`` column (landmarks without
        IDs: the fusers associate the rows).
    measurements : dict, optional
        Filled with ``(robot, stamp_ns) -> true IDs`` of every observation message
        (``UNKNOWN_ID`` for clutter), stamps as the fusers see them; each fuser then
        also keeps its ``association_log``.

    Returns
    -------
    fusers : dict
        ``method -> Fuser`` (``name -> Fuser`` with ``configs``) after the last fusion.
    observers : list of Observer
        One per robot, with their counters.

    """
    sources = [f'/robot{robot + 1}/landmarks' for robot in range(sim.robots)]
    views = [f'/robot{robot + 1}/partial_observations' for robot in range(sim.robots)]
    observers = [Observer(observer_config(sim.config)) for _ in range(sim.robots)]
    fusers = {method: Fuser(FuserConfig(fusion=method, gate_probability=gate_probability,
                                        min_observations=1), sources,
                            partial_sources=views)
              for method in methods} if configs is None else {
                  name: Fuser(config, sources, partial_sources=views)
                  for name, config in configs.items()}
    if measurements is not None:
        for fuser in fusers.values():
            fuser.association_log = []
    period_ns = int(round(FuserConfig().update_period_s * 1e9))
    observation_end = sim.observations_until(int(sim.config.duration_s * 1e9))
    last_stamp = sim.observation_stamp_ns(observation_end - 1) if observation_end else 0
    # Up to the first pose after the last observation, so that it is bracketed.
    pose_end = sim.poses_until(last_stamp) + 1
    next_pose = next_observation = 0
    next_fusion_ns = START_NS + period_ns

    def hand_over(robot, batches):
        for batch in batches:
            for fuser in fusers.values():
                fuser.add_landmarks(sources[robot], LandmarkMessage(
                    batch.stamp_ns, batch.ids, batch.m, batch.P, batch.P_dep,
                    classes=batch.classes, scan=batch.scan), now_ns=now_ns)
                if len(batch.partial_observations):
                    fuser.add_partial_observations(views[robot], batch.stamp_ns,
                                                   batch.partial_observations.columns(),
                                                   now_ns=now_ns)

    while next_pose < pose_end or next_observation < observation_end:
        pose_stamp = sim.pose_stamp_ns(next_pose)
        if next_observation < observation_end and (
                next_pose >= pose_end
                or sim.observation_stamp_ns(next_observation) < pose_stamp):
            now_ns = START_NS + sim.observation_stamp_ns(next_observation)
            for robot, observer in enumerate(observers):
                measured = sim.measure(robot, next_observation)
                columns = {'id': measured.ids, 'range': measured.z[:, 0],
                           'bearing': measured.z[:, 1]}
                if hide_ids:
                    del columns['id']
                if measurements is not None:
                    measurements[(robot, START_NS + measured.stamp_ns)] = measured.ids
                hand_over(robot, observer.add_observations(
                    [ObservationMessage(START_NS + measured.stamp_ns, columns)], now_ns))
            next_observation += 1
        else:
            now_ns = START_NS + pose_stamp
            for robot, observer in enumerate(observers):
                stamp, _, pose, P_pose = sim.reported_pose(robot, next_pose)
                hand_over(robot, observer.add_pose(START_NS + stamp, pose, P_pose, now_ns))
            next_pose += 1
        while now_ns >= next_fusion_ns:
            for fuser in fusers.values():
                fuser.fuse_queued()
            next_fusion_ns += period_ns
    for fuser in fusers.values():
        fuser.fuse_queued()
    return fusers, observers


def frame_averaged_nees(sim, ids, m, P):
    """
    Return each landmark's NEES with the frame error's term replaced by its mean.

    ``tr(P^-1 D(l)) + n^T P^-1 n`` with ``n = m - l - e(l)`` (module notes, scenario
    ``shared_frame``): the same expectation as the NEES, without the spread of the one
    frame draw per run.

    Parameters
    ----------
    sim : landmark_ros.sim.simulation.Simulation
        With a frame error (``frame_error`` not None).
    ids : ndarray of int, shape (K,)
        Fused landmark IDs, all in the simulated world.
    m : ndarray, shape (K, 2)
        Their means [m].
    P : ndarray, shape (K, 2, 2)
        Their covariances [m^2].

    Returns
    -------
    ndarray, shape (K,)

    """
    truth = sim.world.positions[np.searchsorted(sim.world.ids, ids)]
    D = sim.frame_error.point_covariance(truth)
    n = np.asarray(m) - truth - sim.frame_error.point_error(truth)
    P = np.asarray(P)
    return (np.trace(np.linalg.solve(P, D), axis1=-2, axis2=-1)
            + np.einsum('ki,ki->k', n, np.linalg.solve(P, n[..., None])[..., 0]))


def run_seed(config, methods=FUSION_METHODS, gate_probability=0.999, frame_averaged=None):
    """
    Simulate one seed and fuse it with each method.

    Parameters
    ----------
    config : landmark_ros.sim.simulation.SimConfig
        Simulator parameters, with the seed and a finite duration.
    methods : sequence of str
        Fusion methods.
    gate_probability : float
        The fusers' gate.
    frame_averaged : dict, optional
        With a frame error in ``config``: filled with ``method -> list of
        frame_averaged_nees`` of the fused landmarks.

    Returns
    -------
    dict
        ``method -> list of NEES`` of the fused landmarks.

    Raises
    ------
    RuntimeError
        If an observer rejected anything: the study would not be about what the
        nodes publish.

    """
    sim = simulation.Simulation(config)
    fusers, observers = fuse_simulation(sim, methods, gate_probability)
    for robot, observer in enumerate(observers):
        status = observer.status()
        if status.level != 'ok':
            raise RuntimeError(f'observer of robot{robot + 1}: {status.message}')
    truth = sim.world.truth()
    result = {}
    for method, fuser in fusers.items():
        fused_ids, fused_m, fused_P, _, _ = fuser.snapshot()
        landmarks, _ = evaluate(fused_ids, fused_m, fused_P, truth)
        result[method] = [r.nees for r in landmarks]
        if frame_averaged is not None and sim.frame_error is not None:
            frame_averaged[method] = frame_averaged_nees(sim, fused_ids, fused_m,
                                                         fused_P).tolist()
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
        out=None):
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
    out : file, optional
        Where the table goes (``sys.stdout`` at the call).

    Returns
    -------
    list of dict
        One row per scenario and method: ``scenario``, ``fusion``, ``landmarks``,
        ``anees`` (pooled), ``interval`` (its chi-square interval, for reference),
        ``seed_mean`` and ``seed_half_width`` (mean of the per-seed averages and the
        half width of its 95 % confidence interval), ``expected``, ``ok``; with a
        frame error, ``frame_mean`` and ``frame_half_width``, the same of the
        frame-averaged NEES (``frame_averaged_nees``; None otherwise).

    """
    rows = []
    out = sys.stdout if out is None else out
    print(f"{'scenario':<12} {'fusion':<30} {'landmarks':>9} {'ANEES':>6} {'chi2 95 %':>14} "
          f"{'seed mean':>9} {'95 % CI':>14}  expected     verdict  frame-averaged, 95 % CI",
          file=out)
    for scenario in scenarios:
        nees = {method: [] for method in methods}
        per_seed = {method: [] for method in methods}
        frame_per_seed = {method: [] for method in methods}
        for seed in range(seeds):
            config = replace(simulation.SimConfig(), seed=seed, duration_s=duration_s,
                             **SCENARIOS[scenario])
            frame_averaged = {}
            for method, values in run_seed(config, methods,
                                           frame_averaged=frame_averaged).items():
                nees[method] += values
                per_seed[method].append(float(np.mean(values)))
                if method in frame_averaged:
                    frame_per_seed[method].append(float(np.mean(frame_averaged[method])))
        for method in methods:
            anees = float(np.mean(nees[method]))
            interval = anees_interval(len(nees[method]))
            mean, half = _seed_mean(per_seed[method])
            frame_mean, frame_half = _seed_mean(frame_per_seed[method])
            expected = EXPECTED[(scenario, method)]
            ok = verdict(mean, half, expected)
            rows.append({'scenario': scenario, 'fusion': method,
                         'landmarks': len(nees[method]), 'anees': anees, 'interval': interval,
                         'seed_mean': mean, 'seed_half_width': half,
                         'expected': expected, 'ok': ok, 'frame_mean': frame_mean,
                         'frame_half_width': frame_half})
            frame = ('' if frame_mean is None else
                     f'  {frame_mean:5.2f} [{frame_mean - frame_half:5.2f}, '
                     f'{frame_mean + frame_half:5.2f}]')
            print(f'{scenario:<12} {method:<30} {len(nees[method]):9d} {anees:6.2f} '
                  f'[{interval[0]:5.2f}, {interval[1]:5.2f}] {mean:9.2f} '
                  f'[{mean - half:5.2f}, {mean + half:5.2f}]'
                  f"  {expected:<11}  {'PASS' if ok else 'FAIL'}{frame}", file=out)
    return rows


def _seed_mean(values):
    """Return the mean of per-seed values and its 95 % half width (None, None if empty)."""
    if not values:
        return None, None
    if len(values) < 2:
        return float(values[0]), float('nan')
    return (float(np.mean(values)),
            1.96 * float(np.std(values, ddof=1)) / np.sqrt(len(values)))


def main(argv=None):
    """Run the Monte Carlo from the command line; exit 1 if theory is contradicted."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--seeds', type=int, default=50, help='seeds per scenario')
    parser.add_argument('--duration', type=float, default=20.0,
                        help='simulated seconds per seed')
    parser.add_argument('--scenario', choices=sorted(SCENARIOS), action='append',
                        help='scenario (repeatable; default all)')
    parser.add_argument('--fusion', choices=FUSION_METHODS, action='append',
                        help='fusion method (repeatable; default all three)')
    args = parser.parse_args(argv)
    started = time.monotonic()
    print(f'Monte Carlo: {args.seeds} seeds x {args.duration:g} s simulated per scenario, '
          'three robots, 20 landmarks (simulator defaults)')
    rows = run(args.seeds, args.duration, tuple(args.scenario or SCENARIOS),
               tuple(args.fusion or FUSION_METHODS))
    print(f'{time.monotonic() - started:.1f} s')
    return 0 if all(row['ok'] for row in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
